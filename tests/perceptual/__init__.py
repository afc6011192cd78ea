"""Tests of the perceptual features (ST-LPIPS, ID-MRF) with the shipped shift-tolerant weights."""
