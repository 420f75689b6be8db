"""NSD: self-supervised multi-view scene decomposition (Bi-NVS)."""

__version__ = "0.2.0"
