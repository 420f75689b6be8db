"""NeTePu: keypoint-driven neural geometry/texture rendering and re-identification."""
