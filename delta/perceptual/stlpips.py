"""ST-LPIPS: the shift-tolerant learned perceptual image patch similarity (Ghildyal & Liu 2022).

Same formula as the ``stlpips-pytorch`` 0.0.2 package (``LPIPS(net, variant=
"shift_tolerant")``, version 0.1): inputs in [-1, 1] pass the scaling layer
``(x - shift) / scale`` (ImageNet normalisation), each tapped activation is
unit-normalised along channels (``f / (||f|| + 1e-10)``), the squared difference is
weighted per channel by a non-negative 1x1 linear head, averaged over space and
summed over the five layers.
"""

from __future__ import annotations

import os

import torch
from torch import nn

from delta.perceptual.nets import BACKBONES, lpips_alex_state, read_state_dict, split_state_dict
from delta.perceptual.weights import locate_weights


def unit_normalize(feat: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    """``feat`` divided by its L2 norm over channels (dim 1), as the package does."""
    norm = torch.sqrt(torch.sum(feat * feat, dim=1, keepdim=True))
    return feat / (norm + eps)


class STLPIPS(nn.Module):
    """ST-LPIPS distance; ``forward(x, y)`` takes (B,3,H,W) images in [0, 1] and returns (B,).

    ``weights`` is a ``*_shift_tolerant.pth`` file; without it the file is found with
    :func:`delta.perceptual.weights.locate_weights` (installed package or ``cache_dir``).
    All parameters are frozen; the module is in eval mode and stays there.
    """

    def __init__(self, net: str = "alex", weights: str | os.PathLike | None = None,
                 cache_dir: str | os.PathLike | None = None, state: dict | None = None):  # fmt: skip
        super().__init__()
        if net not in BACKBONES:
            raise ValueError(f"net must be one of {sorted(BACKBONES)}, got {net!r}")
        self.net_name = net
        self.net = BACKBONES[net]()
        self.heads = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in self.net.channels)
        self.register_buffer("shift", torch.zeros(1, 3, 1, 1))
        self.register_buffer("scale", torch.ones(1, 3, 1, 1))
        if state is None:
            path = weights if weights is not None else locate_weights(net, cache_dir)
            state = read_state_dict(path)
        else:
            path = "<state dict>"
        backbone, heads, scaling = split_state_dict(state)
        self.net.load_state_dict(backbone, strict=True)
        self.heads.load_state_dict(heads, strict=True)
        if set(scaling) != {"shift", "scale"}:
            raise KeyError(f"{path}: scaling layer has keys {sorted(scaling)}, expected shift and scale")
        with torch.no_grad():
            self.shift.copy_(scaling["shift"])
            self.scale.copy_(scaling["scale"])
        self.weights_path = str(path)
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> STLPIPS:  # a metric: never in training mode
        return super().train(False)

    def normalized_features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Unit-normalised tapped activations of images ``x`` in [0, 1]."""
        z = (2.0 * x - 1.0 - self.shift) / self.scale
        return [unit_normalize(f) for f in self.net(z)]

    def forward(self, x: torch.Tensor, y: torch.Tensor, per_layer: bool = False):
        if x.shape != y.shape or x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"expected two (B,3,H,W) images of the same shape, got {tuple(x.shape)}, {tuple(y.shape)}")
        fx, fy = self.normalized_features(x), self.normalized_features(y)
        layers = [head((a - b) ** 2).mean(dim=(1, 2, 3)) for head, a, b in zip(self.heads, fx, fy)]
        dist = torch.stack(layers, dim=0).sum(dim=0)
        return (dist, layers) if per_layer else dist


def lpips_alex(backbone: str | os.PathLike, lin: str | os.PathLike) -> STLPIPS:
    """Standard LPIPS-Alex (Zhang et al. 2018, v0.1) from the user's weight files (see
    :func:`delta.perceptual.nets.lpips_alex_state`); same formula as ST-LPIPS, plain AlexNet."""
    return STLPIPS("alex-lpips", state=lpips_alex_state(backbone, lin))
