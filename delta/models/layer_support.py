"""Where the capture sees each exterior layer, and a layer confined there for wearing it alone.

An avatar trained in layers (``training.layers: split``) composites its clothing and hair NeRFs, and its
training images see only the front of the two: a layer may hold density behind the other's surface (hair
grown inside a skirt) that no image ever shows and no term of the objective charges. Worn alone (``delta
dress --layers hair``, a layer's own mesh) that density comes out: loose's hair layer alone covered 4.7
times its own mask, behind its dress (``benchmarks/layers_alone.csv``). Charging that density in training
made a whole hair layer vanish (``docs/method.md``); this decides it from the avatar's own frames instead.

Each training frame is rendered with every layer (pixels every ``stride``); where a layer is seen (its
opacity over ``SEEN``) the point at its depth along the ray is taken back to the canonical space (the
kNN blend, as the renderer does), and the cells of a ``cell``-metre grid that hold such points, grown by
``grow`` cells (the layer's thickness behind its seen surface, F_e's reach), are the layer's support.
:class:`Confined` is the layer with no density outside it.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import torch
from torch import nn

from delta.deformers import knn as deformer
from delta.models.image import live_rays, pixel_grid, reach_box

log = logging.getLogger(__name__)

#: a layer counts as seen on a ray where its opacity is over this
SEEN = 0.5
#: training frames (evenly spread) that decide where each layer is seen
SUPPORT_FRAMES = 8
#: the support grid's cell (m) and how many cells it is grown by around the seen points
CELL = 0.02
GROW = 3


@dataclasses.dataclass
class Support:
    """Canonical cells (X, Y, Z) bool of ``cell`` metres from the corner ``lo`` (3,)."""

    lo: torch.Tensor
    cell: float
    cells: torch.Tensor

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) canonical points -> (N,) bool: in a cell of the support."""
        return in_cells(points, self.lo, self.cell, self.cells)


def in_cells(points: torch.Tensor, lo: torch.Tensor, cell: float, cells: torch.Tensor) -> torch.Tensor:
    """(N, 3) points -> (N,) bool: in a set cell of ``cells`` (X, Y, Z) of ``cell`` metres from ``lo`` (3,)."""
    ijk = torch.floor((points - lo.to(points)) / cell).long()
    size = torch.tensor(cells.shape, device=points.device)
    inside = ((ijk >= 0) & (ijk < size)).all(-1)
    out = torch.zeros(len(points), dtype=torch.bool, device=points.device)
    at = ijk[inside]
    out[inside] = cells.to(points.device)[at[:, 0], at[:, 1], at[:, 2]]
    return out


def support_of(points: torch.Tensor, cell: float = CELL, grow: int = GROW) -> Support:
    """The cells holding canonical ``points`` (N, 3), grown by ``grow`` cells (a cube of side 2 grow + 1)."""
    if not len(points):
        return Support(torch.zeros(3), cell, torch.zeros(1, 1, 1, dtype=torch.bool))
    points = points.detach().float().cpu()
    lo = (torch.floor(points.amin(0) / cell) - grow - 1) * cell  # on the world's grid of ``cell``
    ijk = torch.floor((points - lo) / cell).long()
    size = (ijk.amax(0) + grow + 2).tolist()
    cells = torch.zeros(size, dtype=torch.float32)
    cells[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = 1.0
    if grow:
        k = 2 * grow + 1
        cells = nn.functional.max_pool3d(cells[None, None], k, stride=1, padding=grow)[0, 0]
    return Support(lo, cell, cells > 0)


@torch.no_grad()
def seen_points(model, frame: int, stride: int = 2, chunk: int = 16384) -> dict[str, torch.Tensor]:
    """Canonical points (P, 3) where each layer of ``model``'s layered exterior is seen in ``frame`` (its
    pixels every ``stride``)."""
    n = model.resolution
    pixels = pixel_grid(n, device=model.background.device).view(n, n, 2)[::stride, ::stride].reshape(-1, 2)
    mesh = model.posed_mesh(frame)[0]
    pixels = pixels[live_rays(pixels, reach_box(model, frame, mesh.vertices))]  # the others meet nothing
    rs = model.spec.render
    perturb, rs.perturb = rs.perturb, False
    found = {name: [] for name in model.nerf.names}
    try:
        for s in range(0, len(pixels), chunk):
            px = pixels[s : s + chunk]
            r = model.render(frame, px, mesh=mesh, soft=False)
            origins, dirs = model.camera(frame).rays(px)
            for k, name in enumerate(model.nerf.names):
                seen = r.layer_masks[:, k] > SEEN
                if bool(seen.any()):
                    posed = origins[seen] + r.layer_depths[seen, k, None] * dirs[seen]
                    d = deformer.deform(mesh.skinning, posed, rs.k, rs.sigma, rs.max_dist)
                    found[name].append(d.canonical[d.valid])
    finally:
        rs.perturb = perturb
    empty = model.background.new_zeros(0, 3)
    return {name: torch.cat(p) if p else empty for name, p in found.items()}


def layer_supports(model, frames, names, stride: int = 2) -> dict[str, Support]:
    """Each of the ``names`` layers' :class:`Support` over ``frames`` of ``model`` (trained in layers)."""
    t0 = time.perf_counter()
    points = {name: [] for name in names}
    for f in frames:
        seen = seen_points(model, int(f), stride)
        for name in names:
            points[name].append(seen[name])
    out = {name: support_of(torch.cat(p)) for name, p in points.items()}
    for name, sup in out.items():
        if not sum(len(p) for p in points[name]):
            log.warning("layer %s is seen in none of %d training frames: alone, it has no density left", name,
                        len(frames))  # fmt: skip
        log.info("layer %s: seen at %d points in %d frames, %.3f m³ of canonical space with the grown margin "
                 "(%.1f s)", name, sum(len(p) for p in points[name]), len(frames), float(sup.cells.sum()) * sup.cell**3,
                 time.perf_counter() - t0)  # fmt: skip
    return out


class Confined(nn.Module):
    """A layer's field with no density outside its :class:`Support` (the same colours); the support's cells
    are buffers, so they move with the module."""

    def __init__(self, field: nn.Module, support: Support):
        super().__init__()
        self.field, self.cell = field, support.cell
        self.register_buffer("lo", support.lo.float())
        self.register_buffer("cells", support.cells)

    def inside(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) -> (N,) bool: in the support."""
        return in_cells(x, self.lo, self.cell, self.cells)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rgb, sigma = self.field(x)
        return rgb, sigma * self.inside(x).to(sigma.dtype)

    def density(self, x: torch.Tensor) -> torch.Tensor:
        return self.field.density(x) * self.inside(x).to(x.dtype)

    def set_noise(self, std: float, seed: int | None = None) -> None:
        self.field.set_noise(std, seed)

    def color_cell(self) -> float:
        return self.field.color_cell()


def confined_layers(model, train, layers) -> dict[str, Confined]:
    """``layers`` of ``model``'s layered exterior, each confined to where ``SUPPORT_FRAMES`` of its training
    frames ``train`` (indices, evenly spread) see it (the model is left as it is); none for one NeRF or one
    layer (nothing hides behind another)."""
    nerf = model.nerf
    if not layers or len(getattr(nerf, "names", ())) < 2:
        return {}
    train = np.asarray(train)
    frames = train[np.linspace(0, len(train) - 1, min(SUPPORT_FRAMES, len(train))).round().astype(int)]
    supports = layer_supports(model, frames, layers)
    dev = model.background.device
    return {name: Confined(nerf.layers[name], supports[name]).to(dev) for name in layers}
