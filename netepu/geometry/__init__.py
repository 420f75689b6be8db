"""NeTePu's keypoint-driven geometry renderer.

Silhouette, depth and NNOPCS maps, inverse rendering.
"""
