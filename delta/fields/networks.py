"""The avatar's networks: exterior NeRF F_h, vertex fields F_d / F_t, deformation F_e.

Each is an encoding (``pe`` = the paper's MLP with positional encoding, ``grid`` =
multi-resolution dense grids with a small MLP, fast on a CPU) followed by an MLP head.
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import nn

from delta.fields import LAYERS
from delta.fields.encodings import make_encoding, positional_encoding
from delta.fields.spec import FieldSpec

#: Densities are exp(raw) with raw capped here: σ ≤ e^15 ≈ 3.3e6, gradients stay finite.
MAX_LOG_DENSITY = 15.0


class MLP(nn.Module):
    """ReLU MLP with an optional skip connection re-injecting the input."""

    def __init__(self, in_dim: int, out_dim: int, depth: int, width: int, skip: int = -1):
        super().__init__()
        self.skip = skip
        layers, d = [], in_dim
        for i in range(depth):
            layers.append(nn.Linear(d, width))
            d = width + (in_dim if i == skip else 0)
        self.hidden = nn.ModuleList(layers)
        self.out = nn.Linear(d, out_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.features(x))

    def features(self, x: torch.Tensor, pre: list | None = None) -> torch.Tensor:
        """The output layer's input; each hidden layer's pre-activation is appended to ``pre`` when given."""
        h = x
        for i, layer in enumerate(self.hidden):
            z = layer(h)
            if pre is not None:
                pre.append(z)
            h = torch.relu(z)
            if i == self.skip:
                h = torch.cat([h, x], dim=-1)
        return h


def active_units(mlp: MLP, inputs: torch.Tensor) -> list[int]:
    """Per hidden layer of ``mlp``, how many units are active (pre-activation above zero) on at least one
    of ``inputs`` (N, in). A ReLU unit inactive on every input the field meets gets no gradient again:
    a head whose last layer has few left is a constant, whatever it was meant to learn."""
    pre: list[torch.Tensor] = []
    with torch.no_grad():
        mlp.features(inputs, pre)
    return [int((z > 0).any(0).sum()) for z in pre]


def _encoder_and_head(spec: FieldSpec, bounds: torch.Tensor, out_dim: int, extra_in: int = 0):
    enc = make_encoding(spec.encoding, bounds, num_freqs=spec.num_freqs, levels=spec.levels,
                        features=spec.features, base_res=spec.base_res, max_res=spec.max_res)  # fmt: skip
    return enc, MLP(enc.out_dim + extra_in, out_dim, spec.depth, spec.width, spec.skip)


class NeRFField(nn.Module):
    """F_h: canonical point -> (colour in [0, 1], density ≥ 0); no view direction.

    With the ``pe`` encoding one MLP outputs both (the paper's). With ``grid``, density and colour
    read separate grids and heads: the density's gradients (exp activation, mask losses) are orders
    of magnitude larger than the colour's and would otherwise swamp Adam's shared second moments,
    leaving the colour nearly constant.

    ``bounded``: no density outside the box (σ = 0 there): the exterior of a capture that frames part of
    the body lives where the capture shows it (a grid's features fade to zero outside its box, which
    would leave the head's constant response there: haze around the parts the capture never framed).
    """

    def __init__(self, spec: FieldSpec, bounds: torch.Tensor, density_bias: float = -2.0, bounded: bool = False):
        super().__init__()
        self.bounded = bool(bounded)
        self.split = spec.encoding == "grid"
        self.encoding, self.head = _encoder_and_head(spec, bounds, 1 if self.split else 4)
        if self.split:
            res, levels = spec.color_grid(tuple((bounds[1] - bounds[0]).tolist()))
            color = dataclasses.replace(spec, max_res=res, levels=levels)
            self.color_encoding, self.color_head = _encoder_and_head(color, bounds, 3)
        self.relu = spec.density_activation == "relu"
        with torch.no_grad():  # exp: start nearly empty; relu: the MLP's own start, noise keeps it alive
            self.head.out.bias[-1] = 0.0 if self.relu else density_bias
        self.noise_std, self.noise_generator = 0.0, None  # set per training step (set_noise); 0 elsewhere
        # (V,) bool: the body vertices that may not carry this field's density (None: any); derived, not saved
        self.register_buffer("barred_carriers", None, persistent=False)

    def set_noise(self, std: float, seed: int | None = None) -> None:
        """Noise on raw density for the next forward calls (a training step), drawn from ``seed``."""
        self.noise_std = float(std)
        self.noise_generator = torch.Generator().manual_seed(int(seed)) if std > 0 and seed is not None else None

    def _sigma(self, raw: torch.Tensor, noisy: bool) -> torch.Tensor:
        if noisy and self.noise_std > 0:
            noise = torch.randn(raw.shape, generator=self.noise_generator, dtype=raw.dtype)
            raw = raw + self.noise_std * noise.to(raw.device)
        if self.relu:
            return torch.relu(raw).clamp(max=math.exp(MAX_LOG_DENSITY))
        return torch.exp(raw.clamp(max=MAX_LOG_DENSITY))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 3) -> rgb (N, 3), sigma (N,)."""
        out = self.head(self.encoding(x))
        color = self.color_head(self.color_encoding(x)) if self.split else out[:, :3]
        return torch.sigmoid(color), self._in_box(x, self._sigma(out[:, -1], noisy=True))

    def _in_box(self, x: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
        """``sigma`` (N,), zero at points outside the box (the encoding's) when the field is ``bounded``."""
        if not self.bounded:
            return sigma
        inside = ((x >= self.encoding.lo) & (x <= self.encoding.hi)).all(-1)
        return torch.where(inside, sigma, torch.zeros_like(sigma))

    def color_cell(self) -> float:
        """The finest detail of the colour's encoding (world units)."""
        return (self.color_encoding if self.split else self.encoding).finest_cell()

    def raw_density(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) -> the density before its activation (N,); the colour branch is skipped with ``grid``."""
        return self.head(self.encoding(x))[:, -1]

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) -> sigma (N,) alone, never noisy."""
        return self._in_box(x, self._sigma(self.raw_density(x), noisy=False))


class LayeredNeRF(nn.Module):
    """The exterior as one canonical NeRF a layer (clothing, hair), each a :class:`NeRFField`.

    Where they overlap they are one medium of two kinds of particle: densities add and the colour is
    the density-weighted mix, σ = Σ_l σ_l, c = Σ_l (σ_l / σ) c_l, so a ray renders exactly as through
    one NeRF of that density and colour. Each layer's own opacity along a ray is the ray's weights
    times its share σ_l / σ (:func:`delta.render.hybrid.render_rays`), what its parsing mask supervises;
    a layer can then be moved without the other (hair onto another head, a dress onto another body).
    """

    def __init__(self, spec: FieldSpec, bounds: torch.Tensor, names: tuple[str, ...] = LAYERS,
                 density_bias: float = -2.0, bounded: bool = False):  # fmt: skip
        super().__init__()
        unknown = sorted(set(names) - set(LAYERS))
        if unknown or len(set(names)) != len(names) or not names:
            raise ValueError(f"exterior layers {list(names)}: each one of {list(LAYERS)}, at most once")
        self.names = tuple(names)
        self.layers = nn.ModuleDict({n: NeRFField(spec, bounds, density_bias, bounded) for n in self.names})

    @classmethod
    def of(cls, layers: dict[str, NeRFField]) -> "LayeredNeRF":
        """A stack of existing layers (shared, not copied), in :data:`LAYERS` order: one avatar's clothing
        with another's hair, both in the body model's canonical space."""
        names = tuple(n for n in LAYERS if n in layers)
        if set(names) != set(layers) or not names:
            raise ValueError(f"exterior layers {sorted(layers)}: each one of {list(LAYERS)}")
        stack = cls.__new__(cls)
        nn.Module.__init__(stack)
        stack.names = names
        stack.layers = nn.ModuleDict({n: layers[n] for n in names})
        return stack

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 3) -> rgb (N, 3), sigma (N,) of the layers together."""
        return self.with_layers(x)[:2]

    def with_layers(self, x: torch.Tensor, carriers: torch.Tensor | None = None,
                    at: dict[str, torch.Tensor] | None = None) -> tuple[torch.Tensor, ...]:  # fmt: skip
        """(N, 3) -> rgb (N, 3), sigma (N,) together, and each layer's sigma (N, L) in ``names`` order.
        ``carriers`` (N,): the body vertex that carries each point (backward skinning's nearest); a layer
        has no density at points carried by its ``barred_carriers`` (a clothing layer by the head).
        ``at``: a layer's own canonical points (N, 3) of the same samples where another carriage takes it
        there (a hair layer bound to the head); the others read ``x``."""
        at = at or {}
        outs = [self.layers[n](at.get(n, x)) for n in self.names]
        if carriers is not None:  # a layer may be any field (a confined one, another avatar's)
            barred = [getattr(self.layers[n], "barred_carriers", None) for n in self.names]
            outs = [(c, s if b is None else s.masked_fill(b[carriers], 0.0)) for (c, s), b in zip(outs, barred)]
        sigmas = torch.stack([s for _, s in outs], -1)
        sigma = sigmas.sum(-1)
        share = sigmas / sigma.clamp_min(torch.finfo(sigma.dtype).tiny)[:, None]
        rgb = (share[..., None] * torch.stack([c for c, _ in outs], 1)).sum(1)
        return rgb, sigma, sigmas

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) -> sigma (N,) of the layers together, never noisy."""
        return sum(layer.density(x) for layer in self.layers.values())

    def set_noise(self, std: float, seed: int | None = None) -> None:
        for k, layer in enumerate(self.layers.values()):
            layer.set_noise(std, None if seed is None else seed + 1000 * k)

    def color_cell(self) -> float:
        return min(layer.color_cell() for layer in self.layers.values())


def colour_logit(colour: torch.Tensor) -> torch.Tensor:
    """The raw output whose sigmoid is ``colour`` (clamped to [0.02, 0.98]: a finite, trainable start)."""
    c = colour.float().clamp(0.02, 0.98)
    return torch.log(c / (1 - c))


class VertexField(nn.Module):
    """F_d (offsets) or F_t (albedo): canonical template vertex -> (V, C), with an optional free
    per-vertex detail of the raw output (``FieldSpec.vertex_detail``).

    ``kind="offset"``: tanh(raw) · scale, starting at exactly 0; ``kind="albedo"``: sigmoid(raw),
    starting at ``init`` (e.g. the subject's average skin colour), or per vertex at ``init`` moved by
    ``prior`` (V, 3), a fixed addition to the raw output (derived where the field is built, not saved).
    """

    def __init__(self, spec: FieldSpec, bounds: torch.Tensor, kind: str, scale: float = 0.04,
                 init: torch.Tensor | None = None, num_vertices: int = 0, prior: torch.Tensor | None = None):  # fmt: skip
        super().__init__()
        if kind not in ("offset", "albedo"):
            raise ValueError(f"unknown vertex field kind '{kind}'")
        if spec.vertex_detail and num_vertices < 1:
            raise ValueError("vertex_detail needs the mesh's vertex count")
        self.kind, self.scale = kind, scale
        self.encoding, self.head = _encoder_and_head(spec, bounds, 3)
        # (V, 3) per-vertex detail of the raw output (FieldSpec.vertex_detail), or None
        self.detail = nn.Parameter(torch.zeros(num_vertices, 3)) if spec.vertex_detail else None
        if prior is not None and tuple(prior.shape) != (num_vertices, 3):
            raise ValueError(f"prior: shape {tuple(prior.shape)}, expected ({num_vertices}, 3)")
        # (V, 3) fixed raw addition per vertex, or None
        self.register_buffer("prior", None if prior is None else prior.float().clone(), persistent=False)
        with torch.no_grad():
            self.head.out.weight.zero_()  # start exactly at zero offsets / the init colour
            self.head.out.bias.zero_()
            if init is not None:
                self.head.out.bias.copy_(colour_logit(init))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(V, 3) values at the mesh's vertices ``x`` (V, 3), in vertex order when the field has detail. The
        vertices are the template's, the same every call: their encoding is kept (``at_fixed``)."""
        raw = self.head(self.encoding.at_fixed(x))
        per_vertex = [t for t in (self.detail, self.prior) if t is not None]
        if per_vertex:
            if len(x) != len(per_vertex[0]):
                raise ValueError(f"{len(x)} points: a field with per-vertex detail or a prior reads its "
                                 f"{len(per_vertex[0])} vertices")  # fmt: skip
            raw = raw + sum(per_vertex)
        return torch.tanh(raw) * self.scale if self.kind == "offset" else torch.sigmoid(raw)


class DeformationField(nn.Module):
    """F_e: (canonical point, kNN-weighted posed body point[, time]) -> Δx_c, starting at exactly 0.

    The posed body point (detached) tells the network the pose; its output is scaled
    by ``scale`` so that early training barely moves the canonical point. With
    ``time_freqs`` > 0 it also reads :func:`time_features` of the frame's time: clothing
    that sways is not a function of the pose alone (the paper's F_e sees only the pose).
    """

    def __init__(self, spec: FieldSpec, bounds: torch.Tensor, scale: float = 0.05, pose_freqs: int = 4,
                 time_freqs: int = 0):  # fmt: skip
        super().__init__()
        self.scale, self.pose_freqs, self.time_freqs = scale, pose_freqs, time_freqs
        extra = 3 * (1 + 2 * pose_freqs) + 2 * time_freqs
        self.encoding, self.head = _encoder_and_head(spec, bounds, 3, extra_in=extra)
        with torch.no_grad():
            self.head.out.weight.zero_()
            self.head.out.bias.zero_()

    def forward(self, x_c: torch.Tensor, posed_ref: torch.Tensor, time: torch.Tensor | None = None) -> torch.Tensor:
        """``time``: (2 time_freqs,) features of the frame (None: zeros, the time-free deformation)."""
        return torch.tanh(self.head(self._inputs(x_c, posed_ref, time))) * self.scale

    def _inputs(self, x_c: torch.Tensor, posed_ref: torch.Tensor, time: torch.Tensor | None) -> torch.Tensor:
        cond = [positional_encoding(posed_ref.detach(), self.pose_freqs)]
        if self.time_freqs:
            t = time if time is not None else x_c.new_zeros(2 * self.time_freqs)
            cond.append(t.to(x_c).expand(len(x_c), -1))
        return torch.cat([self.encoding(x_c)] + cond, dim=-1)

    def box_points(self, points: int, seed: int = 0) -> torch.Tensor:
        """(points, 3) canonical points drawn uniformly (seeded) in the field's box."""
        g = torch.Generator().manual_seed(seed)
        lo, hi = self.encoding.lo, self.encoding.hi
        return lo + (hi - lo) * torch.rand(points, 3, generator=g).to(lo)

    def active_units(self, times: torch.Tensor | None = None, points: int = 4096, seed: int = 0) -> list[int]:
        """:func:`active_units` of the head over ``points`` drawn uniformly in the field's box, each taken as
        its own pose cue, at each of ``times`` (T, 2 time_freqs) time inputs (None: the time-free input)."""
        x = self.box_points(points, seed)
        rows = [None] if times is None else list(times)
        with torch.no_grad():
            inputs = torch.cat([self._inputs(x, x, t) for t in rows])
        return active_units(self.head, inputs)


def time_features(tau: torch.Tensor, freqs: int) -> torch.Tensor:
    """(..., 2 freqs) cosine-basis features of normalised times τ ∈ [0, 1]: sin(kπτ), cos(kπτ), k = 1..freqs.

    A NaN time (a frame outside the training sequence: a novel pose) gets zeros: the input on
    which training (``dynamics.dropout`` of its steps) teaches F_e the time-free deformation.
    """
    k = torch.arange(1, freqs + 1, dtype=tau.dtype, device=tau.device) * math.pi
    a = tau[..., None] * k
    f = torch.cat([torch.sin(a), torch.cos(a)], dim=-1)
    return torch.where(torch.isnan(tau)[..., None], torch.zeros_like(f), f)
