"""Points read at their mirror image through a body: a grid of cells, each with its own mirror plane.

A cell with a plane ``m`` (a coordinate along ``axis``) sends a point x to x with ``x[axis]`` replaced by
``m - x[axis]``; a cell without one (NaN) and a point outside the grid stay where they are. With ``m`` the sum
of where a line along the axis enters and leaves a body, a point a distance behind the body's back goes to the
same distance before its front: the clothing's back is read from its front.

Shapes: N points; the grid (X, Y, Z) cells.
"""

from __future__ import annotations

import dataclasses

import torch

from delta.geometry.raymesh import ray_mesh_hits


@dataclasses.dataclass
class MirrorGrid:
    lo: torch.Tensor
    """(3,) the grid's lower corner."""
    cell: float
    """A cell's edge (metres)."""
    planes: torch.Tensor
    """(X, Y, Z) each cell's mirror plane along ``axis`` (NaN: none)."""
    axis: int = 2

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) the points, each at its mirror image where its cell has a plane."""
        flat, inside = cell_of(x, self.lo, self.cell, tuple(self.planes.shape))
        m = self.planes.to(x).reshape(-1)[flat]
        has = inside & m.isfinite()
        if not bool(has.any()):
            return x
        flipped = torch.where(has, torch.nan_to_num(m) - x[:, self.axis], x[:, self.axis])
        return torch.cat([x[:, : self.axis], flipped[:, None], x[:, self.axis + 1 :]], -1)


def cell_of(points: torch.Tensor, lo: torch.Tensor, cell: float, size: tuple[int, int, int]):
    """Each point's cell of a grid (``lo`` its corner, ``size`` cells along x, y, z), flat (N,) int64, and
    whether the point lies in the grid (N,) bool (outside: a border cell's index, not to be read)."""
    bound = torch.tensor(size, device=points.device)
    at = torch.floor((points.detach() - lo.to(points)) / cell).long()
    inside = ((at >= 0) & (at < bound)).all(-1) & torch.isfinite(points.detach()).all(-1)
    at = torch.minimum(at.clamp_min(0), bound - 1)
    return (at[:, 0] * size[1] + at[:, 1]) * size[2] + at[:, 2], inside


def through_planes(points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, axis: int = 2,
                   sign: float = 1.0) -> torch.Tensor:  # fmt: skip
    """(N,) for points outside a closed mesh (outward normals), the sum of where the line from each point along
    ``sign`` × the ``axis`` direction enters the mesh and where it leaves it again (its mirror plane through the
    mesh: :class:`MirrorGrid`); NaN where the line meets no face, or first meets one from inside."""
    p = points.detach().double()
    v = vertices.detach().double()
    d = torch.zeros_like(p)
    d[:, axis] = sign
    first = ray_mesh_hits(v, faces, p, d)
    tri = v[faces[first.face.clamp_min(0)]]
    normal = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    entering = first.hit & ((normal * d).sum(-1) < 0)
    out = torch.full((len(p),), float("nan"), dtype=torch.float64, device=p.device)
    if not bool(entering.any()):
        return out
    ids = torch.nonzero(entering).squeeze(1)
    eps = 1e-6
    start = p[ids] + (first.t[ids] + eps)[:, None] * d[ids]
    second = ray_mesh_hits(v, faces, start, d[ids])
    ok = second.hit
    enter = p[ids, axis] + sign * first.t[ids]
    leave = p[ids, axis] + sign * (first.t[ids] + eps + second.t)
    out[ids[ok]] = (enter + leave)[ok]
    return out
