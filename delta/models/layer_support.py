"""Where the capture sees each exterior layer, and a layer confined there for wearing it alone.

An avatar trained in layers (``training.layers: split``) composites its clothing and hair NeRFs, and its
training images see only the front of the two: a layer may hold density behind the other's surface (hair
grown inside a skirt) that no image ever shows and no term of the objective charges. Worn alone (``delta
dress --layers hair``, a layer's own mesh) that density comes out: loose's hair layer alone covered 4.7
times its own mask, behind its dress (``benchmarks/layers_alone.csv``). Charging that density in training
made a whole hair layer vanish (``docs/method.md``); this decides it from the avatar's own frames instead.

Each training frame is rendered with every layer; where a layer is seen (its opacity over ``SEEN`` and
the capture's parsing gives it) the point at its depth along the ray is taken back to the canonical
space (the kNN blend, as the renderer does), and the cells of a ``cell``-metre grid that hold such
points, grown by ``grow`` cells (the layer's thickness behind its seen surface, F_e's reach), are the
layer's support. Some layers are never worn under others (``NEVER_UNDER``: hair is not worn under
clothing): where the parsing gives such another layer and not this one, the cells from the exterior's
front to the body leave this layer's grown margin; its seen cells stay. Loose's hair layer held the
dress's red 1-5 cm behind the dress's surface beside the hair, inside the margin.
:class:`Confined` is the layer with no density outside it.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import torch
from torch import nn

from delta.cameras.models import metres_per_pixel
from delta.deformers import knn as deformer
from delta.geometry.raymesh import keep_scene, ray_mesh_hits
from delta.losses import layer_targets
from delta.models.image import live_rays, reach_box

log = logging.getLogger(__name__)

#: a layer counts as seen on a ray where its opacity is over this
SEEN = 0.5
#: training frames (evenly spread) that decide where each layer is seen
SUPPORT_FRAMES = 8
#: the support grid's cell (m) and how many cells it is grown by around the seen points
CELL = 0.02
GROW = 3
#: the layers each layer is never worn under: its density behind their seen surface is none of its own
NEVER_UNDER = {"hair": ("clothing",)}


def may_cover(name: str, names) -> tuple[str, ...]:
    """The layers of ``names`` that may lie over layer ``name`` (long hair over the clothing): all the others
    but those it is never worn under."""
    return tuple(o for o in names if o != name and o not in NEVER_UNDER.get(name, ()))


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


def support_of(points: torch.Tensor, cell: float = CELL, grow: int = GROW,
               behind: torch.Tensor | None = None) -> Support:  # fmt: skip
    """The cells holding canonical ``points`` (N, 3), grown by ``grow`` cells (a cube of side 2 grow + 1),
    less the grown cells that hold a point of ``behind`` (M, 3) (behind another layer's surface) and none
    of ``points``."""
    if not len(points):
        return Support(torch.zeros(3), cell, torch.zeros(1, 1, 1, dtype=torch.bool))
    points = points.detach().float().cpu()
    lo = (torch.floor(points.amin(0) / cell) - grow - 1) * cell  # on the world's grid of ``cell``
    ijk = torch.floor((points - lo) / cell).long()
    size = (ijk.amax(0) + grow + 2).tolist()
    seen = torch.zeros(size, dtype=torch.float32)
    seen[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = 1.0
    cells = seen
    if grow:
        k = 2 * grow + 1
        cells = nn.functional.max_pool3d(seen[None, None], k, stride=1, padding=grow)[0, 0]
    cells = cells > 0
    if behind is not None and len(behind):
        carved = torch.zeros_like(cells)
        at = torch.floor((behind.detach().float().cpu() - lo) / cell).long()
        at = at[((at >= 0) & (at < torch.tensor(size))).all(-1)]
        carved[at[:, 0], at[:, 1], at[:, 2]] = True
        cells &= ~carved | (seen > 0)
    return Support(lo, cell, cells)


def ray_step(camera, vertices: torch.Tensor, stride: float) -> float:
    """Pixels between the support's rays: ``stride``, or fewer where that spans more than half a ``CELL`` at the
    body (``vertices`` (V, 3), posed): the median pixel's width there."""
    mpp = float(metres_per_pixel(camera, vertices.detach()).median())
    return min(float(stride), CELL / 2 / max(mpp, 1e-9))


def ray_grid(n: int, step: float, device=None) -> torch.Tensor:
    """(R, 2) ray positions ``step`` pixels apart over an n×n image (the first half a step in)."""
    axis = torch.arange(step / 2, n, step, dtype=torch.float32, device=device)
    v, u = torch.meshgrid(axis, axis, indexing="ij")
    return torch.stack([u, v], -1).reshape(-1, 2)


@torch.no_grad()
def seen_points(model, frame: int, masks: dict[str, torch.Tensor] | None = None, stride: int = 2,
                chunk: int = 16384) -> tuple[dict, dict]:  # fmt: skip
    """Canonical points where each layer of ``model``'s layered exterior is seen in ``frame``, and where it
    is ruled out; two dicts of (P, 3) by layer name.

    The rays are ``stride`` pixels apart, or closer where a pixel spans more than half a cell on the body
    (a small image): every cell the layers pass through is met (:func:`ray_step`).

    Seen: the point at the layer's depth on rays where its opacity is over ``SEEN`` and its mask in
    ``masks`` ((n, n) each, the capture's parsing; None: opacity alone) is set. Ruled out: on rays whose
    masks give a layer it is never worn under (``NEVER_UNDER``) and not itself, where the exterior is
    seen, the points every half cell from half a cell before the front (the nearer seen layer's depth)
    to a cell into the body (to ``GROW`` + 1 cells behind the front where the ray misses it)."""
    n = model.resolution
    mesh = model.posed_mesh(frame)[0]
    keep_scene(mesh.vertices, mesh.faces)  # the chunks all query one scene
    pixels = ray_grid(n, ray_step(model.camera(frame), mesh.vertices, stride), model.background.device)
    pixels = pixels[live_rays(pixels, reach_box(model, frame, mesh.vertices))]  # the others meet nothing
    rs = model.spec.render
    perturb, rs.perturb = rs.perturb, False
    names = model.nerf.names
    found = {name: [] for name in names}
    ruled_out = {name: [] for name in names}

    def canonical(posed, name):
        d = deformer.deform(mesh.skinning, posed, rs.k, rs.sigma, rs.max_dist)
        c = d.canonical
        if name == "hair" and mesh.skinning.head_index is not None:  # the hair's own carriage, as it renders
            c = deformer.head_bound(mesh.skinning, posed, c, d.distance)
        return c[d.valid]

    try:
        for s in range(0, len(pixels), chunk):
            px = pixels[s : s + chunk]
            r = model.render(frame, px, mesh=mesh, soft=False)
            origins, dirs = model.camera(frame).rays(px)
            ij = px.long().clamp(0, n - 1)
            given = {name: (masks[name].to(px.device)[ij[:, 1], ij[:, 0]] > 0.5) if masks else None for name in names}
            opaque = r.layer_masks > SEEN
            front = torch.where(opaque, r.layer_depths, torch.full_like(r.layer_depths, float("inf"))).amin(1)
            for k, name in enumerate(names):
                seen = opaque[:, k] if given[name] is None else opaque[:, k] & given[name]
                if bool(seen.any()):
                    found[name].append(canonical(origins[seen] + r.layer_depths[seen, k, None] * dirs[seen], name))
                over = [given[o] for o in NEVER_UNDER.get(name, ()) if o in names and given[o] is not None]
                if given[name] is None or not over:
                    continue
                out = torch.stack(over).any(0) & ~given[name] & front.isfinite()
                if not bool(out.any()):
                    continue
                o, d, t0 = origins[out], dirs[out], front[out] - CELL / 2
                hits = ray_mesh_hits(mesh.vertices, mesh.faces, o, d)
                t1 = torch.where(hits.hit, hits.t, front[out] + GROW * CELL) + CELL  # a cell into the body
                steps = torch.arange(int(float((t1 - t0).max()) / (CELL / 2)) + 1, device=o.device) * (CELL / 2)
                t = t0[:, None] + steps
                ruled_out[name].append(canonical((o[:, None] + t[..., None] * d[:, None])[t <= t1[:, None]], name))
    finally:
        rs.perturb = perturb
    empty = model.background.new_zeros(0, 3)
    cat = lambda pts: {name: torch.cat(p) if p else empty for name, p in pts.items()}  # noqa: E731
    return cat(found), cat(ruled_out)


def layer_supports(model, data, frames, names, stride: int = 2) -> dict[str, Support]:
    """Each of the ``names`` layers' :class:`Support` over ``frames`` of ``model`` (trained in layers) and
    ``data`` (its :class:`delta.data.frames.FrameData`: the masks; without a hair mask, opacity alone)."""
    t0 = time.perf_counter()
    points = {name: [] for name in names}
    ruled_out = {name: [] for name in names}
    for f in frames:
        masks = layer_targets(data.exterior[f].float(), data.hair[f].float()) if data.hair is not None else None
        seen, out = seen_points(model, int(f), masks, stride)
        for name in names:
            points[name].append(seen[name])
            ruled_out[name].append(out[name])
    out = {name: support_of(torch.cat(points[name]), behind=torch.cat(ruled_out[name])) for name in names}
    for name, sup in out.items():
        if not sum(len(p) for p in points[name]):
            log.warning("layer %s is seen in none of %d training frames: alone, it has no density left", name,
                        len(frames))  # fmt: skip
        log.info("layer %s: seen at %d points in %d frames, ruled out at %d, %.3f m³ of canonical space with "
                 "the grown margin (%.1f s)", name, sum(len(p) for p in points[name]), len(frames),
                 sum(len(p) for p in ruled_out[name]), float(sup.cells.sum()) * sup.cell**3,
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

    @property
    def barred_carriers(self) -> torch.Tensor | None:
        """The confined field's (:meth:`delta.fields.networks.LayeredNeRF.with_layers`)."""
        return getattr(self.field, "barred_carriers", None)

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


def confined_layers(model, data, layers) -> dict[str, Confined]:
    """``layers`` of ``model``'s layered exterior, each confined to where ``SUPPORT_FRAMES`` of its training
    frames (``data.train``, evenly spread) see it (the model is left as it is); none for one NeRF or one
    layer (nothing hides behind another)."""
    nerf = model.nerf
    if not layers or len(getattr(nerf, "names", ())) < 2:
        return {}
    train = np.asarray(data.train)
    frames = train[np.linspace(0, len(train) - 1, min(SUPPORT_FRAMES, len(train))).round().astype(int)]
    supports = layer_supports(model, data, frames, layers)
    dev = model.background.device
    return {name: Confined(nerf.layers[name], supports[name]).to(dev) for name in layers}
