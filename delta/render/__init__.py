"""Differentiable rendering pieces: silhouettes and volume rendering."""
