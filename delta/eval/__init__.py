"""Evaluation: image metrics, held-out renders, geometry against ground truth, mesh export."""
