"""Thin command lines: nsd-train, nsd-eval, nsd-export."""
