"""Evaluation: held-out renders scored with ``delta.metrics``, geometry against ground truth, mesh export."""
