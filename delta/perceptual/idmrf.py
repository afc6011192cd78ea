"""DELTA's semantic loss: ID-MRF (Wang et al., NeurIPS 2018) or a VGG perceptual loss.

ID-MRF on one feature layer, for generated features ``G`` and target features ``T``:

1. centre both by the target mean, then unit-normalise every feature vector;
2. cosine distance ``d_ij = (1 - <t_i, g_j>) / 2`` between target patch ``i`` and
   generated patch ``j`` (1x1 patches);
3. relative distance ``r_ij = d_ij / (min_k d_kj + eps)`` (over target patches);
4. contextual similarity ``cs_ij = softmax_i((1 - r_ij) / h)``, bandwidth ``h``;
5. loss ``-log(mean_i max_j cs_ij)``: every target patch should be the nearest
   neighbour of some generated patch (the *implicit diversification*).

Defaults follow the common PyTorch implementation that DELTA and SCARF use: layers
``relu3_2`` and ``relu4_2`` with weight 1.0 each plus a "content" term that is the
same MRF loss on ``relu4_2`` (weight 1.0), ``h = 0.5``, ``eps = 1e-5``, centring by the
target's per-position channel mean (``center="channel"``; ``"spatial"`` centres by
the per-channel spatial mean, as in the contextual loss of Mechrez et al.), and the
per-image losses summed over the batch. The features are the shift-tolerant VGG16
shipped with ``stlpips-pytorch`` (a VGG16, not the VGG19 of the original: torchvision's
ImageNet weights are not shippable here).
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import nn

from delta.perceptual.nets import IMAGENET_MEAN, IMAGENET_STD, load_backbone
from delta.perceptual.weights import locate_weights

IDMRF_LAYERS = {"relu3_2": 1.0, "relu4_2": 1.0}
IDMRF_CONTENT_LAYERS = {"relu4_2": 1.0}
#: the blocks of SCARF's VGG16 perceptual loss (torchvision features[:4], [4:9], [9:16], [16:23])
PERCEPTUAL_LAYERS = {"relu1_2": 1.0, "relu2_2": 1.0, "relu3_3": 1.0, "relu4_3": 1.0}


def _unit(x: torch.Tensor, eps: float) -> torch.Tensor:
    # smooth at zero (a constant image centres to exactly zero features)
    return x / torch.sqrt((x * x).sum(dim=1, keepdim=True) + eps * eps)


def mrf_loss(gen: torch.Tensor, tar: torch.Tensor, h: float = 0.5, eps: float = 1e-5,
             center: str = "channel") -> torch.Tensor:  # fmt: skip
    """ID-MRF loss of generated features ``gen`` against ``tar``, both (B,C,H,W); returns (B,)."""
    if gen.dim() != 4 or gen.shape[:2] != tar.shape[:2]:
        shapes = f"{tuple(gen.shape)}, {tuple(tar.shape)}"
        raise ValueError(f"feature maps must be (B,C,H,W) with equal B and C, got {shapes}")
    if center == "channel":
        if gen.shape != tar.shape:
            raise ValueError("center='channel' needs feature maps of equal size")
        mu = tar.mean(dim=1, keepdim=True)
    elif center == "spatial":
        mu = tar.mean(dim=(2, 3), keepdim=True)
    else:
        raise ValueError(f"center must be 'channel' or 'spatial', got {center!r}")
    g = _unit(gen - mu, eps).flatten(2)  # (B, C, Ng)
    t = _unit(tar - mu, eps).flatten(2)  # (B, C, Nt)
    cos = torch.bmm(t.transpose(1, 2), g)  # (B, Nt, Ng)
    dist = ((1.0 - cos) * 0.5).clamp_min(0.0)
    rel = dist / (dist.min(dim=1, keepdim=True).values + eps)
    cs = torch.softmax((1.0 - rel) / h, dim=1)  # normalised over target patches
    best = cs.max(dim=2).values  # (B, Nt): best match of every target patch
    return -torch.log(best.mean(dim=1))


def idmrf_loss(features_x: Mapping[str, torch.Tensor], features_y: Mapping[str, torch.Tensor],
               layers: Mapping[str, float] = IDMRF_LAYERS,
               content_layers: Mapping[str, float] | None = IDMRF_CONTENT_LAYERS,
               h: float = 0.5, eps: float = 1e-5, center: str = "channel",
               reduction: str = "sum") -> torch.Tensor:  # fmt: skip
    """ID-MRF over named feature maps of the generated (``x``) and target (``y``) images.

    ``layers`` are the "style" terms, ``content_layers`` the extra content terms of the
    common implementation (``None`` or ``{}`` leaves them out). ``reduction``: "sum"
    (the common implementation), "mean" or "none" over the batch.
    """
    terms: list[tuple[str, float]] = list(layers.items()) + list((content_layers or {}).items())
    per_image = sum(w * mrf_loss(features_x[n], features_y[n], h=h, eps=eps, center=center) for n, w in terms)
    return _reduce(per_image, reduction)


def perceptual_loss(features_x: Mapping[str, torch.Tensor], features_y: Mapping[str, torch.Tensor],
                    layers: Mapping[str, float] = PERCEPTUAL_LAYERS,
                    reduction: str = "mean") -> torch.Tensor:  # fmt: skip
    """Sum over ``layers`` of the weighted mean absolute feature difference."""
    per_image = sum(w * (features_x[n] - features_y[n]).abs().mean(dim=(1, 2, 3)) for n, w in layers.items())
    return _reduce(per_image, reduction)


def _reduce(per_image: torch.Tensor, reduction: str) -> torch.Tensor:
    if reduction == "sum":
        return per_image.sum()
    if reduction == "mean":
        return per_image.mean()
    if reduction == "none":
        return per_image
    raise ValueError(f"reduction must be 'sum', 'mean' or 'none', got {reduction!r}")


class SemanticLoss(nn.Module):
    """Semantic loss between rendered and target patches (B,3,H,W) in [0, 1].

    ``kind="idmrf"`` (DELTA's body stage-2 loss) or ``"perceptual"`` (its head loss).
    The shift-tolerant VGG16 is frozen; gradients flow to ``rendered`` only, the
    target's features are computed without a graph. ``resize`` (perceptual only)
    bilinearly resizes both inputs to ``resize x resize`` first, as SCARF does with 224.
    """

    def __init__(self, kind: str = "idmrf", weights: str | os.PathLike | None = None,
                 cache_dir: str | os.PathLike | None = None, layers: Mapping[str, float] | None = None,
                 content_layers: Mapping[str, float] | None = IDMRF_CONTENT_LAYERS, h: float = 0.5,
                 eps: float = 1e-5, center: str = "channel", reduction: str | None = None,
                 resize: int | None = None):  # fmt: skip
        super().__init__()
        if kind not in ("idmrf", "perceptual"):
            raise ValueError(f"kind must be 'idmrf' or 'perceptual', got {kind!r}")
        self.kind = kind
        self.vgg = load_backbone("vgg", weights if weights is not None else locate_weights("vgg", cache_dir))
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1))
        default = IDMRF_LAYERS if kind == "idmrf" else PERCEPTUAL_LAYERS
        self.layers = dict(layers if layers is not None else default)
        self.content_layers = dict(content_layers or {}) if kind == "idmrf" else {}
        self.h, self.eps, self.center = h, eps, center
        self.reduction = reduction or ("sum" if kind == "idmrf" else "mean")
        self.resize = resize
        self._names = sorted(set(self.layers) | set(self.content_layers))

    def train(self, mode: bool = True) -> SemanticLoss:  # the frozen VGG stays in eval mode
        return super().train(False)

    def _features(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        if x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"expected (B,3,H,W) images, got {tuple(x.shape)}")
        if self.resize is not None:
            x = F.interpolate(x, size=(self.resize, self.resize), mode="bilinear", align_corners=False)
        return self.vgg.features((x - self.mean) / self.std, self._names)

    def forward(self, rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        fx = self._features(rendered)
        with torch.no_grad():
            fy = self._features(target)
        if self.kind == "perceptual":
            return perceptual_loss(fx, fy, self.layers, reduction=self.reduction)
        return idmrf_loss(fx, fy, self.layers, self.content_layers, h=self.h, eps=self.eps,
                          center=self.center, reduction=self.reduction)  # fmt: skip
