"""Label-free cues from the median background.

Foreground evidence, the visual hull, proposals, triangulation.
"""
