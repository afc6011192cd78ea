"""Backward deformation from posed space to the canonical space."""
