"""Candidate faces of rays that leave one point (a camera's centre), binned in the rays' own image.

Rays from one point are a central projection. A triangle wholly in front of the point projects to the
triangle of its projected corners, so a ray can meet only the faces whose projected boxes hold the ray's
own projection. The faces' boxes are binned on a grid laid over the rays' projections, and each ray's
candidates are its cell's faces: a short, fixed sequence of tensor operations (a sort, a count and two
``repeat_interleave``), where walking a box hierarchy takes rounds of small operations. On a GPU, where
a training step's camera rays are launch-bound, that is the difference (``benchmarks/step_profile.py
--trace``). Faces with a corner at, behind or all but at the point are candidates of every ray.

The caller decides each candidate pair exactly (:func:`delta.geometry.raymesh._confirm`); the binning
only has to be conservative, and the boxes are grown by far more than the projection's rounding.

Shapes: R rays, F faces, G cells a side, M candidate (ray, face) pairs.
"""

from __future__ import annotations

import dataclasses
from typing import Iterator

import torch

MIN_COS = 0.1
"""Rays more than acos(0.1) (84°) from their mean direction are not binned (None: the caller walks its
hierarchy); a projection plane cannot hold a wider pencil."""
FACES_PER_CELL = 8
"""The grid has about F / this many cells (G a side, at most :data:`MAX_SIDE`)."""
MAX_SIDE = 256
MAX_BINNED = 1 << 24
"""(face, cell) entries above this (faces far larger than a cell): not binned."""


def shared_origin(origins: torch.Tensor) -> bool:
    """Whether every ray (R, 3) leaves the same point (exactly: a camera's rays share its centre)."""
    return origins.shape[0] > 0 and bool((origins == origins[0]).all())


def shared_direction(dirs: torch.Tensor) -> bool:
    """Whether every ray (R, 3) has the same direction (exactly: an orthographic camera's rays)."""
    return dirs.shape[0] > 0 and bool((dirs == dirs[0]).all()) and bool(dirs[0].abs().amax() > 0)


@dataclasses.dataclass
class Bins:
    """Faces binned on a grid over the rays' projections."""

    ray_cell: torch.Tensor
    """(R,) int64 the cell of each ray."""
    cell_start: torch.Tensor
    """(G*G,) int64 each cell's first entry in ``cell_faces``."""
    cell_count: torch.Tensor
    """(G*G,) int64 faces binned in each cell."""
    cell_faces: torch.Tensor
    """(E,) int64 face indices, grouped by cell, ascending within a cell."""
    everywhere: torch.Tensor
    """(S,) int64 faces with a corner at, behind or all but at the point: candidates of every ray."""

    def pairs(self, chunk: int) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """(ray, face) candidate pairs, (M,) each, in batches of whole rays of about ``chunk`` pairs."""
        R = self.ray_cell.shape[0]
        count = self.cell_count[self.ray_cell] + self.everywhere.shape[0]  # (R,)
        end = torch.cumsum(count, 0)
        total = int(end[-1]) if R else 0
        if total <= chunk:  # one batch (a training step's): its size is known, nothing more to read back
            yield self._pairs(0, R, total)
            return
        cuts = torch.searchsorted(end, torch.arange(chunk, total, chunk, device=end.device), right=True)
        bounds = [0, *sorted(set(cuts.tolist()) - {0, R}), R]
        for lo, hi in zip(bounds[:-1], bounds[1:]):
            yield self._pairs(lo, hi)

    def _pairs(self, lo: int, hi: int, size: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The pairs of rays lo..hi; ``size``: their number when known (then no count is read back)."""
        dev = self.ray_cell.device
        rays = torch.arange(lo, hi, device=dev)
        binned = self.cell_count[self.ray_cell[lo:hi]]
        S = self.everywhere.shape[0]
        out = None if size is None else size - S * (hi - lo)
        ray = rays.repeat_interleave(binned, output_size=out)
        first = torch.cumsum(binned, 0) - binned  # each ray's first pair
        rank = torch.arange(ray.shape[0], device=dev) - first.repeat_interleave(binned, output_size=ray.shape[0])
        face = self.cell_faces[self.cell_start[self.ray_cell[ray]] + rank]
        if S:
            ray = torch.cat([ray, rays.repeat_interleave(S)])
            face = torch.cat([face, self.everywhere.repeat(hi - lo)])
        return ray, face


@torch.no_grad()
def bin_faces(tri: torch.Tensor, origin: torch.Tensor, dirs: torch.Tensor) -> Bins | None:
    """The faces ``tri`` (F, 3, 3) binned for rays ``origin`` (3,) + t ``dirs`` (R, 3), R >= 1; None when
    the rays spread wider than :data:`MIN_COS` allows or the faces are too large for the grid."""
    dtype = tri.dtype
    dn = torch.nn.functional.normalize(dirs.to(dtype), dim=1)
    axis = dn.mean(0)
    length = axis.norm()
    axis = axis / length
    cos = dn @ axis
    if not all(torch.stack([length > 0, (cos > MIN_COS).all()]).tolist()):  # one read back for both
        return None
    basis = _plane(axis)  # rows: the projection plane's axes, depth
    ray_uv = (dn @ basis[:2].T) / cos[:, None]  # (R, 2)
    rel = (tri - origin.to(dtype)) @ basis.T  # (F, 3, 3) corners in the pencil's frame
    depth = rel[..., 2]
    near = torch.finfo(dtype).eps ** 0.5 * rel.abs().amax()  # nearer corners would project out of range
    front = (depth > near).all(1)
    everywhere = ((depth > 0).any(1) & ~front).nonzero().squeeze(1)  # straddling the point's plane
    ids = front.nonzero().squeeze(1)
    uv = rel[ids, :, :2] / depth[ids, :, None]  # (Ff, 3, 2)
    pad = torch.finfo(dtype).eps ** 0.5 * (1 + uv.abs().amax((1, 2)))  # (Ff,): far more than its rounding
    f_lo, f_hi = uv.amin(1) - pad[:, None], uv.amax(1) + pad[:, None]
    return _grid(ids, f_lo, f_hi, ray_uv, everywhere)


def _plane(axis: torch.Tensor) -> torch.Tensor:
    """(3, 3) rows: two axes of the plane across ``axis`` (unit), then ``axis``."""
    helper = torch.nn.functional.one_hot(axis.abs().argmin(), 3).to(axis.dtype)
    e1 = torch.nn.functional.normalize(torch.linalg.cross(axis, helper), dim=0)
    return torch.stack([e1, torch.linalg.cross(axis, e1), axis])


@torch.no_grad()
def bin_faces_parallel(tri: torch.Tensor, origins: torch.Tensor, direction: torch.Tensor) -> Bins | None:
    """The faces ``tri`` (F, 3, 3) binned for parallel rays ``origins`` (R, 3) + t ``direction`` (3,), R >= 1
    (an orthographic camera's): the projection along the direction is a parallel one, so every face projects
    to the triangle of its projected corners and none is a candidate everywhere. None when the faces are too
    large for the grid."""
    dtype = tri.dtype
    basis = _plane(torch.nn.functional.normalize(direction.to(dtype), dim=0))[:2]
    ray_uv = origins.to(dtype) @ basis.T  # (R, 2)
    uv = tri @ basis.T  # (F, 3, 2)
    pad = torch.finfo(dtype).eps ** 0.5 * (1 + uv.abs().amax((1, 2)))
    ids = torch.arange(tri.shape[0], device=tri.device)
    return _grid(ids, uv.amin(1) - pad[:, None], uv.amax(1) + pad[:, None], ray_uv, ids[:0])


def _grid(ids, f_lo, f_hi, ray_uv, everywhere) -> Bins | None:
    """Faces ``ids`` with projected boxes [f_lo, f_hi] (Ff, 2) binned on a grid over the rays' projections
    ``ray_uv`` (R, 2); None when their (face, cell) entries exceed :data:`MAX_BINNED`."""
    dev = ray_uv.device
    lo, hi = ray_uv.amin(0), ray_uv.amax(0)
    side = int(min(MAX_SIDE, max(1, round((max(len(ids), 1) / FACES_PER_CELL) ** 0.5))))
    cell = ((hi - lo) / side).clamp_min(1e-12 * (1 + lo.abs().amax()))
    overlaps = ((f_hi >= lo) & (f_lo <= hi)).all(1)
    ids, f_lo, f_hi = ids[overlaps], f_lo[overlaps], f_hi[overlaps]
    c0 = ((f_lo - lo) / cell).floor().clamp(0, side - 1).long()  # (Fo, 2) first and last cell per axis
    c1 = ((f_hi - lo) / cell).floor().clamp(0, side - 1).long()
    n = c1 - c0 + 1
    per_face = n[:, 0] * n[:, 1]
    total = int(per_face.sum())
    if total > MAX_BINNED:
        return None
    which = torch.arange(len(ids), device=dev).repeat_interleave(per_face, output_size=total)
    k = torch.arange(total, device=dev) - (torch.cumsum(per_face, 0) - per_face).repeat_interleave(
        per_face, output_size=total
    )
    cu = c0[which, 0] + k // n[which, 1]
    cv = c0[which, 1] + k % n[which, 1]
    cells = cu * side + cv
    order = torch.argsort(cells, stable=True)  # by cell; within a cell by face index
    count = torch.bincount(cells, minlength=side * side)
    ray_cell = ((ray_uv - lo) / cell).floor().clamp(0, side - 1).long()
    return Bins(ray_cell=ray_cell[:, 0] * side + ray_cell[:, 1], cell_start=torch.cumsum(count, 0) - count,
                cell_count=count, cell_faces=ids[which[order]], everywhere=everywhere)  # fmt: skip
