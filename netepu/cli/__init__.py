"""Thin command line: netepu-train (geometry and texture stages)."""
