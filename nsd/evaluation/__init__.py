"""The one metrics package.

Decomposition, rendered maps, keypoints, identities, re-identification.
"""
