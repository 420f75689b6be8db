"""The NSD / Bi-NVS model.

Detector, focal spatial transformer, encoder, decoder, association, compositor.
"""
