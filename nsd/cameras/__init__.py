"""Calibrated cameras.

One camera, a rig, a batch as tensors, projection with distortion, calibration files.
"""
