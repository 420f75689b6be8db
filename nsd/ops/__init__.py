"""Small shared operations.

Boxes of masks (one convention per name), IoU matrices, matching, unit vectors.
"""
