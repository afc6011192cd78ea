"""Which points of a surface a parallel view sees: the outside of a mesh among occluders.

Shapes: N points, V vertices, F faces, D view directions.
"""

from __future__ import annotations

import math

import torch

from delta.geometry.raymesh import keep_scene, ray_mesh_hits


def view_ring(azimuths: int, elevations_deg, up: int = 1) -> torch.Tensor:
    """(D, 3) unit view directions (where the view looks) around the axis ``up`` (0, 1, 2): ``azimuths``
    evenly spaced turns at each elevation of ``elevations_deg`` (degrees; positive looks down towards
    −up, as a camera above a person does), D = azimuths × len(elevations_deg)."""
    across = [i for i in range(3) if i != up]
    dirs = []
    for e in elevations_deg:
        e = math.radians(float(e))
        for k in range(azimuths):
            a = 2 * math.pi * k / azimuths
            d = [0.0, 0.0, 0.0]
            d[across[0]], d[across[1]], d[up] = math.cos(e) * math.sin(a), math.cos(e) * math.cos(a), -math.sin(e)
            dirs.append(d)
    return torch.tensor(dirs, dtype=torch.float64)


def seen_along(points: torch.Tensor, normals: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor,
               directions: torch.Tensor, tol: float, facing: float = 0.0) -> torch.Tensor:  # fmt: skip
    """(N,) bool: the points some view of ``directions`` (D, 3) sees, looking along it from outside the mesh.

    A point is seen along d where its normal faces the view (n · d < −``facing``, ``normals`` (N, 3) unit)
    and the first face of the mesh (V, 3), (F, 3) on the line towards it along d lies no more than ``tol``
    before it: the point itself (a face through it) or a face within ``tol`` of it. The mesh holds the points'
    own surface and whatever may hide it; a point on no face of it is seen where nothing lies before it."""
    p = points.detach().double()
    n = normals.detach().double()
    v = vertices.detach().double()
    seen = torch.zeros(len(p), dtype=torch.bool, device=p.device)
    if not len(p):
        return seen
    centre = v.mean(0) if len(v) else p.mean(0)
    reach = float(torch.cat([p, v]).sub(centre).norm(dim=-1).max()) * 2 + 1.0  # from outside everything
    keep_scene(v, faces)  # every view's rays query one scene
    for d in directions.to(p):
        d = d / d.norm()
        todo = ~seen & ((n @ d) < -facing)
        if not bool(todo.any()):
            continue
        q = p[todo]
        origins = q - reach * d
        hits = ray_mesh_hits(v, faces, origins, d.expand_as(q).contiguous())
        seen[todo] = ~hits.hit | (hits.t >= reach - tol)
    return seen


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(V, 3) unit area-weighted vertex normals of a mesh (V, 3), (F, 3); zero at a vertex on no face."""
    v = vertices.detach()
    tri = v[faces]
    n = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)  # twice the area, outward for CCW
    out = torch.zeros_like(v).index_add_(0, faces.reshape(-1), n.repeat_interleave(3, 0))
    return out / out.norm(dim=-1, keepdim=True).clamp_min(1e-12)


@torch.no_grad()
def visible_vertices(vertices: torch.Tensor, faces: torch.Tensor, camera, tol: float = 0.005,
                     facing: float | None = None) -> torch.Tensor:  # fmt: skip
    """(V,) bool: the vertices a camera sees: inside its image and first on the ray from the camera to
    them (no face of the mesh closer than ``tol`` metres before them); with ``facing``, also turned
    towards the camera: the vertex normal's cosine with the direction to the camera above it.

    The ray is the physical one (pinhole: from the camera's centre through the vertex; orthographic:
    along -z), so lens distortion does not enter.
    """
    normals = vertex_normals(vertices.detach().double(), faces) if facing is not None else None
    return visible_points(vertices, vertices, faces, camera, tol, normals, facing)


@torch.no_grad()
def visible_points(points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, camera, tol: float = 0.005,
                   normals: torch.Tensor | None = None, facing: float | None = None) -> torch.Tensor:  # fmt: skip
    """(N,) bool: the points (N, 3) a camera sees past a mesh (V, 3), (F, 3): inside its image and no face
    closer than ``tol`` metres before them on the ray from the camera; with ``normals`` (N, 3) and ``facing``,
    also turned towards the camera by a cosine above ``facing`` (:func:`visible_vertices`)."""
    v = vertices.detach().double()
    p = points.detach().double()
    uv, _ = camera.project(p)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height)
    if hasattr(camera, "center"):
        origins = camera.center.double().expand_as(p)
        dirs = p - origins
        reach = dirs.norm(dim=-1)
        dirs = dirs / reach.clamp_min(1e-12)[:, None]
    else:
        start = float(torch.cat([p[:, 2], v[:, 2]]).max()) + 1.0
        origins = torch.cat([p[:, :2], torch.full_like(p[:, :1], start)], dim=-1)
        dirs = torch.zeros_like(p)
        dirs[:, 2] = -1.0
        reach = start - p[:, 2]
    if normals is not None and facing is not None:
        inside &= (normals.to(p) * -dirs).sum(-1) > facing
    hits = ray_mesh_hits(v, faces, origins, dirs)
    first = ~hits.hit | (hits.t >= reach - tol)
    return (inside & first).cpu()
