"""Decomposing frames with a trained model.

Single image (NSD), multi-view (with the hull), tracking.
"""
