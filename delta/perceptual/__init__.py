"""Perceptual features with shipped weights: ST-LPIPS for evaluation, ID-MRF / VGG loss for training.

The weights are the shift-tolerant VGG16 and AlexNet of the ``stlpips-pytorch``
0.0.2 wheel, loaded into this package's own network definitions (the package itself
is never imported: it needs torchvision). Submodules import torch lazily from here.
"""

from delta.perceptual.weights import fetch_weights, locate_weights

__all__ = ["fetch_weights", "locate_weights", "STLPIPS", "SemanticLoss", "idmrf_loss", "mrf_loss"]


def __getattr__(name: str):
    if name == "STLPIPS":
        from delta.perceptual.stlpips import STLPIPS

        return STLPIPS
    if name in ("SemanticLoss", "idmrf_loss", "mrf_loss"):
        from delta.perceptual import idmrf

        return getattr(idmrf, name)
    raise AttributeError(f"module 'delta.perceptual' has no attribute {name!r}")
