"""First ray-mesh hits whose distance and barycentrics are differentiable.

The search for the first hit is discrete and runs without gradients, either in
Embree (through trimesh + embreex, float32 internally) or as a brute-force
chunked Möller–Trumbore in torch. The distance ``t`` and the barycentrics of
each found (ray, face) pair are then recomputed in torch from the vertex
tensor, so gradients reach vertices, ray origins and ray directions, and the
values carry the precision of the inputs rather than Embree's float32.

Shapes: R rays, V vertices, F faces, C channels. Device and dtype follow the
inputs.
"""

from __future__ import annotations

import dataclasses
import weakref

import numpy as np
import torch

_CHUNK_PAIRS = 1 << 20
"""Ray-face pairs held at once by the brute-force torch search."""


@dataclasses.dataclass
class RayHits:
    """First hit of each ray (t > 0) on a triangle mesh."""

    hit: torch.Tensor
    """(R,) bool, the ray hits the mesh."""
    t: torch.Tensor
    """(R,) hit = origin + t * dir; +inf where no hit. Differentiable."""
    face: torch.Tensor
    """(R,) int64 face index, -1 where no hit."""
    bary: torch.Tensor
    """(R, 3) barycentric weights wrt the face's 3 vertices, zeros where no hit. Differentiable."""


def embree_available() -> bool:
    """Whether trimesh's Embree intersector (embreex) can be imported."""
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector  # noqa: F401
    except ImportError:
        return False
    return True


def _safe_div(num: torch.Tensor, den: torch.Tensor, floor: torch.Tensor) -> torch.Tensor:
    """num / den with |den| clamped to >= floor, keeping den's sign (sign(0) = +1)."""
    sign = torch.where(den < 0, -torch.ones_like(den), torch.ones_like(den))
    return num / (sign * torch.maximum(den.abs(), floor))


def moller_trumbore(origins, dirs, a, b, c):
    """Möller–Trumbore ray-plane hit in the frame of a triangle, with guarded divisions.

    Args:
        origins, dirs: (..., 3) rays.
        a, b, c: (..., 3) triangle corners (broadcast against the rays).
    Returns:
        (t, u, v, det), each (...,): the ray meets the triangle's plane at
        origin + t * dir = (1 - u - v) a + u b + v c. ``det`` is the raw
        determinant (0 for a ray parallel to the plane). The determinant is
        clamped away from 0 (sign kept) by ``eps * |dir| * L^2`` with L the
        largest of the edge lengths and the origin's offset from ``a``, so a
        parallel or grazing ray gives finite values and gradients.
    """
    origins, dirs, a, b, c = torch.broadcast_tensors(origins, dirs, a, b, c)
    e1, e2 = b - a, c - a
    pvec = torch.linalg.cross(dirs, e2, dim=-1)
    det = (e1 * pvec).sum(-1)
    tvec = origins - a
    qvec = torch.linalg.cross(tvec, e1, dim=-1)
    eps = torch.finfo(det.dtype).eps
    with torch.no_grad():
        length = torch.stack([e1.norm(dim=-1), e2.norm(dim=-1), tvec.norm(dim=-1)], -1).amax(-1)
        floor = eps * dirs.norm(dim=-1) * length**2 + torch.finfo(det.dtype).tiny / eps
    u = _safe_div((tvec * pvec).sum(-1), det, floor)
    v = _safe_div((dirs * qvec).sum(-1), det, floor)
    t = _safe_div((e2 * qvec).sum(-1), det, floor)
    return t, u, v, det


def _face_tables(tri: torch.Tensor) -> dict:
    """Per-face terms for :func:`_search_chunk` from (F, 3, 3) corners, each (F, 3) or (F,)."""
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = torch.linalg.cross(e1, e2, dim=-1)
    e2xa, axe1 = torch.linalg.cross(e2, a, dim=-1), torch.linalg.cross(a, e1, dim=-1)
    norms = {k: x.norm(dim=-1) for k, x in dict(e1=e1, e2=e2, e2xa=e2xa, axe1=axe1).items()}
    return dict(e1=e1, e2=e2, n=n, e2xa=e2xa, axe1=axe1, an=(a * n).sum(-1), **{"|" + k: v for k, v in norms.items()})


def _search_chunk(o, d, ft: dict, tol: float, tri: torch.Tensor) -> torch.Tensor:
    """(Rc,) first-hit face of a chunk of rays (-1: none).

    Möller–Trumbore with the ray-face products expanded into (Rc, 3) x (3, F)
    matmuls (no divisions; det's sign is folded into the tests). The expansion
    loses precision to cancellation (``o x d`` is large for a scene far from the
    origin), so its inside tests carry a per-pair rounding bound and only propose
    candidates: each candidate pair is decided by the direct Möller–Trumbore on
    ``o - a`` (:func:`_confirm`), whose error does not grow with the distance to
    the origin. Without that, a ray nearly parallel to a face of a scene 1 km from
    the origin was taken to hit it up to 5 cm outside its edge.
    """
    m = torch.linalg.cross(o, d, dim=-1)
    det = -(d @ ft["n"].T)
    u = m @ ft["e2"].T - d @ ft["e2xa"].T
    v = -(m @ ft["e1"].T) - d @ ft["axe1"].T
    tn = o @ ft["n"].T - ft["an"]
    sign = torch.where(det < 0, -1.0, 1.0).to(det.dtype)
    u, v, tn, det = u * sign, v * sign, tn * sign, det.abs()
    mn, dn = m.norm(dim=-1)[:, None], d.norm(dim=-1)[:, None]
    err_u = tol * (mn * ft["|e2"] + dn * ft["|e2xa"])
    err_v = tol * (mn * ft["|e1"] + dn * ft["|axe1"])
    scale = dn * ft["|e1"] * ft["|e2"]
    ok = (det > tol * scale) & (u >= -err_u) & (v >= -err_v) & (u + v <= det + err_u + err_v + tol * scale) & (tn > 0)
    ray, face = ok.nonzero(as_tuple=True)
    t = torch.full(ok.shape, torch.inf, dtype=o.dtype, device=o.device)
    t[ray, face] = _confirm(o[ray], d[ray], tri[face], tol)
    best_t, best = t.min(dim=1)
    return torch.where(torch.isfinite(best_t), best, -1)


def _confirm(o, d, tri, tol: float) -> torch.Tensor:
    """(P,) hit distance of candidate (ray, face) pairs by the direct Möller–Trumbore, +inf where the ray
    misses the face (barycentrics outside [0, 1] by more than ``tol``, a ray parallel to the plane, t <= 0)."""
    t, u, v, det = moller_trumbore(o, d, tri[:, 0], tri[:, 1], tri[:, 2])
    scale = d.norm(dim=-1) * (tri[:, 1] - tri[:, 0]).norm(dim=-1) * (tri[:, 2] - tri[:, 0]).norm(dim=-1)
    hit = (det.abs() > tol * scale) & (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol) & (t > 0)
    return torch.where(hit, t, torch.inf)


@torch.no_grad()
def _search_torch(vertices, faces, origins, dirs) -> torch.Tensor:
    """(R,) first-hit face by brute force over all faces (-1: none), in float64 where available."""
    work = torch.float64 if vertices.device.type != "mps" else torch.float32
    o, d = origins.detach().to(work), dirs.detach().to(work)
    R, F = o.shape[0], faces.shape[0]
    if R == 0 or F == 0:
        return torch.full((R,), -1, dtype=torch.int64, device=o.device)
    tri = vertices.detach().to(work)[faces]
    ft = _face_tables(tri)
    step = max(1, _CHUNK_PAIRS // F)
    tol = 64 * torch.finfo(work).eps
    return torch.cat([_search_chunk(o[s : s + step], d[s : s + step], ft, tol, tri) for s in range(0, R, step)])


class _SceneCache:
    """The Embree scene of the last mesh cast against, reused while the same vertex and face tensors
    (the same objects, unmodified: their ``_version`` unchanged) come back: a whole-image render casts
    its rays in chunks against one posed mesh. Weak references: a freed tensor never matches a new one
    that reuses its memory."""

    def __init__(self):
        self.key, self.intersector = None, None

    def get(self, vertices: torch.Tensor, faces: torch.Tensor):
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        if self.key is not None:
            v_ref, v_ver, f_ref, f_ver = self.key
            if v_ref() is vertices and f_ref() is faces and v_ver == vertices._version and f_ver == faces._version:
                return self.intersector
        mesh = trimesh.Trimesh(vertices.detach().cpu().double().numpy(), faces.detach().cpu().numpy(), process=False)
        self.intersector = RayMeshIntersector(mesh)
        self.key = (weakref.ref(vertices), vertices._version, weakref.ref(faces), faces._version)
        return self.intersector


_SCENES = _SceneCache()


def _search_embree(vertices, faces, origins, dirs) -> torch.Tensor:
    """(R,) first-hit face from Embree (float32 internally; -1: none)."""
    R = origins.shape[0]
    face = np.full(R, -1, dtype=np.int64)
    if R and faces.shape[0]:
        # No locations: they are recomputed in torch, and trimesh's location step drops near-parallel rays.
        tri, ray = _SCENES.get(vertices, faces).intersects_id(
            origins.detach().cpu().double().numpy(),
            dirs.detach().cpu().double().numpy(),
            multiple_hits=False,
            return_locations=False,
        )
        face[ray] = tri
    return torch.from_numpy(face).to(origins.device)


def ray_mesh_hits(vertices, faces, origins, dirs, backend: str = "auto") -> RayHits:
    """First hit of each ray on a triangle mesh, differentiable in t and barycentrics.

    Args:
        vertices: (V, 3) float, may require grad.
        faces: (F, 3) int64.
        origins: (R, 3) ray origins; dirs: (R, 3) directions (any non-zero length;
            t is measured in units of |dir|).
        backend: "embree", "torch" (brute force; small meshes) or "auto" (Embree
            when importable).
    Returns:
        :class:`RayHits`. Barycentrics are clamped to [0, 1] and renormalised,
        which only changes rays through an edge or vertex (rounding); t is the
        exact hit on the found face's plane in the inputs' precision.
    """
    if backend == "auto":
        backend = "embree" if embree_available() else "torch"
    if backend == "embree":
        face = _search_embree(vertices, faces, origins, dirs)
    elif backend == "torch":
        face = _search_torch(vertices, faces, origins, dirs)
    else:
        raise ValueError(f"unknown backend {backend!r}; expected 'auto', 'embree' or 'torch'")
    hit = face >= 0
    idx = hit.nonzero().squeeze(1)
    dtype = torch.promote_types(vertices.dtype, torch.promote_types(origins.dtype, dirs.dtype))
    corners = vertices.to(dtype)[faces[face[idx]]]  # (H, 3, 3)
    o, d = origins.to(dtype)[idx], dirs.to(dtype)[idx]
    t_h, u, v, _ = moller_trumbore(o, d, corners[:, 0], corners[:, 1], corners[:, 2])
    bary_h = torch.stack([1 - u - v, u, v], -1).clamp(0, 1)
    bary_h = bary_h / bary_h.sum(-1, keepdim=True).clamp_min(torch.finfo(dtype).eps)
    R = origins.shape[0]
    t = torch.full((R,), torch.inf, dtype=dtype, device=origins.device).index_put((idx,), t_h)
    bary = torch.zeros((R, 3), dtype=dtype, device=origins.device).index_put((idx,), bary_h)
    return RayHits(hit=hit, t=t, face=face, bary=bary)


def interpolate(hits: RayHits, faces, vertex_values) -> torch.Tensor:
    """Barycentric interpolation of per-vertex values at the hits.

    Args:
        hits: from :func:`ray_mesh_hits`.
        faces: (F, 3) the faces the hits refer to.
        vertex_values: (V, C) values (or (V,) for one channel).
    Returns:
        (R, C) (or (R,)) interpolated values, zeros where no hit; differentiable
        wrt ``vertex_values`` and through ``hits.bary``.
    """
    squeeze = vertex_values.dim() == 1
    values = vertex_values[:, None] if squeeze else vertex_values
    if faces.shape[0] == 0:
        out = values.new_zeros((hits.face.shape[0], values.shape[1]))
        return out[:, 0] if squeeze else out
    corners = values[faces[hits.face.clamp_min(0)]]  # (R, 3, C)
    out = (hits.bary.to(values.dtype)[..., None] * corners).sum(1)
    out = torch.where(hits.hit[:, None], out, torch.zeros_like(out))
    return out[:, 0] if squeeze else out
