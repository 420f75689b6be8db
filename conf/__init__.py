"""Hydra configuration tree of the toolkit (shipped as package data)."""
