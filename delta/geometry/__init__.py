"""Differentiable geometry queries: ray-mesh hits and interpolation."""
