"""Plain-torch feature extractors in the shift-tolerant variant of ``stlpips-pytorch`` 0.0.2.

The shift-tolerant networks (Ghildyal & Liu, ECCV 2022) differ from torchvision's
VGG16 / AlexNet in three ways:

* every stride-2 max pool becomes a stride-1 max pool followed by a *blur pool*: a
  depthwise 3x3 binomial filter ``[1,2,1]^T [1,2,1] / 16`` applied with stride 2
  after **reflection** padding of 2 pixels on every side (the package's ``pad_more``);
* AlexNet's first convolution runs at stride 1 (not 4) and is followed directly by a
  blur pool (before its ReLU), so ``relu1`` is at half, not a quarter, resolution;
* the LPIPS taps are the same as the package's: VGG ``relu1_2 .. relu5_3`` and
  AlexNet ``relu1 .. relu5``.

Modules are numbered exactly like the package's ``slice{1..5}`` sequentials, so the
shipped state dicts load after stripping their ``net.`` prefix, with ``strict=True``.
Blur filters are buffers and are loaded from the file as well.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence

import torch
import torch.nn.functional as F
from torch import nn

#: ImageNet statistics; ST-LPIPS's scaling layer is the same map applied to inputs in [-1, 1]
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class BlurPool2d(nn.Module):
    """Anti-aliased stride-2 subsampling: reflect-pad, depthwise binomial blur, subsample."""

    def __init__(self, channels: int, stride: int = 2, pad: int = 2):
        super().__init__()
        taps = torch.tensor([1.0, 2.0, 1.0])
        kernel = torch.outer(taps, taps)
        kernel = kernel / kernel.sum()
        self.register_buffer("filt", kernel.expand(channels, 1, 3, 3).clone())
        self.stride = stride
        self.pad = pad

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.pad(x, (self.pad,) * 4, mode="reflect")
        return F.conv2d(x, self.filt, stride=self.stride, groups=x.shape[1])

    def extra_repr(self) -> str:
        return f"channels={self.filt.shape[0]}, stride={self.stride}, reflect_pad={self.pad}"


class _SlicedBackbone(nn.Module):
    """A feature stack stored as ``slice1..sliceK`` sequentials with globally numbered children.

    ``layers`` is a list of ``(name, module)`` in order; ``slice_ends`` gives the global
    index one past the last layer of every slice. Layer names let callers tap any
    intermediate activation (``relu3_2`` ...); ``taps`` are the LPIPS outputs.
    """

    taps: tuple[str, ...] = ()

    def __init__(self, layers: Sequence[tuple[str, nn.Module]], slice_ends: Sequence[int]):
        super().__init__()
        self.layer_names: list[str] = [name for name, _ in layers]
        self._slice_of: list[int] = []
        start = 0
        for s, end in enumerate(slice_ends, start=1):
            seq = nn.Sequential()
            for i in range(start, end):
                seq.add_module(str(i), layers[i][1])
                self._slice_of.append(s)
            self.add_module(f"slice{s}", seq)
            start = end
        if start != len(layers):
            raise ValueError("slice_ends must cover every layer")

    def _modules_in_order(self) -> Iterable[nn.Module]:
        for s in range(1, len(set(self._slice_of)) + 1):
            yield from getattr(self, f"slice{s}").children()

    def features(self, x: torch.Tensor, names: Iterable[str] | None = None) -> dict[str, torch.Tensor]:
        """The activations named in ``names`` (default: the LPIPS taps), keyed by name.

        Stops after the deepest requested layer.
        """
        wanted = list(self.taps if names is None else names)
        unknown = [n for n in wanted if n not in self.layer_names]
        if unknown:
            raise KeyError(f"unknown layer(s) {unknown}; known: {self.layer_names}")
        last = max(self.layer_names.index(n) for n in wanted)
        out: dict[str, torch.Tensor] = {}
        for i, module in enumerate(self._modules_in_order()):
            x = module(x)
            name = self.layer_names[i]
            if name in wanted:
                out[name] = x
            if i == last:
                break
        return out

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The LPIPS taps, shallow to deep."""
        feats = self.features(x, self.taps)
        return [feats[n] for n in self.taps]


class ShiftTolerantVGG16(_SlicedBackbone):
    """VGG16 convolutional trunk (13 convs) with blur-pooled max pools; taps relu{1_2,..,5_3}."""

    taps = ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3")
    channels = (64, 128, 256, 512, 512)
    _blocks = ((64, 64), (128, 128), (256, 256, 256), (512, 512, 512), (512, 512, 512))

    def __init__(self):
        layers: list[tuple[str, nn.Module]] = []
        slice_ends = []
        c_in = 3
        for b, widths in enumerate(self._blocks, start=1):
            if b > 1:  # the pool that ends the previous block opens this slice
                layers.append((f"pool{b - 1}", nn.MaxPool2d(kernel_size=2, stride=1)))
                layers.append((f"blur{b - 1}", BlurPool2d(c_in)))
            for k, c_out in enumerate(widths, start=1):
                layers.append((f"conv{b}_{k}", nn.Conv2d(c_in, c_out, kernel_size=3, padding=1)))
                layers.append((f"relu{b}_{k}", nn.ReLU()))
                c_in = c_out
            slice_ends.append(len(layers))
        super().__init__(layers, slice_ends)


def _alex_tail() -> list[tuple[str, nn.Module]]:
    """conv3 .. relu5, the same in both AlexNet variants."""
    return [
        ("conv3", nn.Conv2d(192, 384, kernel_size=3, padding=1)),
        ("relu3", nn.ReLU()),
        ("conv4", nn.Conv2d(384, 256, kernel_size=3, padding=1)),
        ("relu4", nn.ReLU()),
        ("conv5", nn.Conv2d(256, 256, kernel_size=3, padding=1)),
        ("relu5", nn.ReLU()),
    ]


class ShiftTolerantAlexNet(_SlicedBackbone):
    """AlexNet trunk with a stride-1 first conv and blur pools; taps relu1..relu5."""

    taps = ("relu1", "relu2", "relu3", "relu4", "relu5")
    channels = (64, 192, 384, 256, 256)

    def __init__(self):
        layers = [
            ("conv1", nn.Conv2d(3, 64, kernel_size=11, stride=1, padding=2)),
            ("blur1", BlurPool2d(64)),
            ("relu1", nn.ReLU()),
            ("pool1", nn.MaxPool2d(kernel_size=3, stride=1)),
            ("blur1b", BlurPool2d(64)),
            ("conv2", nn.Conv2d(64, 192, kernel_size=5, padding=2)),
            ("relu2", nn.ReLU()),
            ("pool2", nn.MaxPool2d(kernel_size=3, stride=1)),
            ("blur2", BlurPool2d(192)),
        ] + _alex_tail()
        super().__init__(layers, (3, 7, 11, 13, 15))


class AlexNet(_SlicedBackbone):
    """torchvision's AlexNet trunk, the backbone of standard LPIPS; taps relu1..relu5.

    Layers are numbered like torchvision's ``features.{i}`` (conv1 = 0 … relu5 = 11), so a
    torchvision state dict maps key by key (:func:`lpips_alex_state`).
    """

    taps = ("relu1", "relu2", "relu3", "relu4", "relu5")
    channels = (64, 192, 384, 256, 256)

    def __init__(self):
        layers = [
            ("conv1", nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2)),
            ("relu1", nn.ReLU()),
            ("pool1", nn.MaxPool2d(kernel_size=3, stride=2)),
            ("conv2", nn.Conv2d(64, 192, kernel_size=5, padding=2)),
            ("relu2", nn.ReLU()),
            ("pool2", nn.MaxPool2d(kernel_size=3, stride=2)),
        ] + _alex_tail()
        super().__init__(layers, (2, 5, 8, 10, 12))


BACKBONES = {"vgg": ShiftTolerantVGG16, "alex": ShiftTolerantAlexNet, "alex-lpips": AlexNet}
#: standard LPIPS's scaling layer (inputs in [-1, 1] to ImageNet statistics)
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)


def lpips_alex_state(backbone: str | os.PathLike, lin: str | os.PathLike) -> dict[str, torch.Tensor]:
    """An ST-LPIPS-layout state dict of standard LPIPS-Alex from the user's two files.

    ``backbone``: torchvision's AlexNet weights (``alexnet-owt-7be5be79.pth``, keys
    ``features.{i}.weight/bias``; the classifier is ignored); ``lin``: the ``lpips``
    package's ``weights/v0.1/alex.pth`` (keys ``lin{k}.model.1.weight``).
    """
    trunk, heads = read_state_dict(backbone), read_state_dict(lin)
    slice_of = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}
    state = {}
    for i, s in slice_of.items():
        for kind in ("weight", "bias"):
            key = f"features.{i}.{kind}"
            if key not in trunk:
                raise KeyError(f"{backbone}: no '{key}'; expected torchvision's AlexNet state dict")
            state[f"net.slice{s}.{i}.{kind}"] = trunk[key]
    for k in range(5):
        key = f"lin{k}.model.1.weight"
        if key not in heads:
            raise KeyError(f"{lin}: no '{key}'; expected the lpips package's alex.pth (v0.1)")
        state[key] = heads[key]
    state["scaling_layer.shift"] = torch.tensor(LPIPS_SHIFT).view(1, 3, 1, 1)
    state["scaling_layer.scale"] = torch.tensor(LPIPS_SCALE).view(1, 3, 1, 1)
    return state


def read_state_dict(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """A shipped ``*_shift_tolerant.pth`` (a flat tensor dict; loaded without pickled code)."""
    return torch.load(path, map_location="cpu", weights_only=True)


def split_state_dict(state: dict[str, torch.Tensor]) -> tuple[dict, dict, dict]:
    """``(backbone, heads, scaling)`` parts of an ST-LPIPS file, prefixes stripped.

    ``heads`` maps ``"{k}.weight"`` (from ``lin{k}.model.1.weight``); ``scaling`` has
    ``shift`` and ``scale``. Unknown keys raise ``KeyError``.
    """
    net, heads, scaling = {}, {}, {}
    for key, value in state.items():
        if key.startswith("net."):
            net[key[len("net.") :]] = value
        elif key.startswith("lin") and key.endswith(".model.1.weight"):
            heads[f"{int(key[3 : key.index('.')])}.weight"] = value
        elif key.startswith("scaling_layer."):
            scaling[key[len("scaling_layer.") :]] = value
        else:
            raise KeyError(f"unexpected key {key!r} in an ST-LPIPS state dict")
    return net, heads, scaling


def load_backbone(net: str, path: str | os.PathLike, requires_grad: bool = False) -> _SlicedBackbone:
    """The shift-tolerant ``net`` ("vgg" or "alex") with the file's weights, in eval mode."""
    if net not in BACKBONES:
        raise ValueError(f"net must be one of {sorted(BACKBONES)}, got {net!r}")
    model = BACKBONES[net]()
    backbone_state, _, _ = split_state_dict(read_state_dict(path))
    model.load_state_dict(backbone_state, strict=True)
    model.eval()
    model.requires_grad_(requires_grad)
    return model
