"""First ray-mesh hits whose distance and barycentrics are differentiable.

The search for the first hit is discrete and runs without gradients, either in
Embree (embreex, float32 internally; CPU) or in torch on the inputs' device,
walking a box hierarchy of the faces (:mod:`delta.geometry.clusters`). The
distance ``t`` and the barycentrics of
each found (ray, face) pair are then recomputed in torch from the vertex
tensor, so gradients reach vertices, ray origins and ray directions, and the
values carry the precision of the inputs rather than Embree's float32.

Shapes: R rays, V vertices, F faces, C channels. Device and dtype follow the
inputs.
"""

from __future__ import annotations

import dataclasses
import weakref
from typing import Callable

import numpy as np
import torch

from delta.devices import host_paths
from delta.geometry import clusters, pencil

FACE_LEAF = clusters.LEAF
"""Faces per leaf of the torch search's hierarchy."""
_CHUNK_RAYS = 1 << 14
"""Rays walked through the face hierarchy at once by the torch search."""
_CHUNK_PAIRS = 1 << 20
"""Candidate ray-face pairs decided at once by the torch search."""


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
    """Whether Embree (embreex) can be imported."""
    try:
        from embreex import rtcore_scene  # noqa: F401
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


def _confirm(o, d, tri, tol: float) -> torch.Tensor:
    """(P,) hit distance of candidate (ray, face) pairs by the direct Möller–Trumbore, +inf where the ray
    misses the face (barycentrics outside [0, 1] by more than ``tol``, a ray parallel to the plane, t <= 0).
    Its error does not grow with the scene's distance from the origin (it works on ``o - a``)."""
    t, u, v, det = moller_trumbore(o, d, tri[:, 0], tri[:, 1], tri[:, 2])
    scale = d.norm(dim=-1) * (tri[:, 1] - tri[:, 0]).norm(dim=-1) * (tri[:, 2] - tri[:, 0]).norm(dim=-1)
    hit = (det.abs() > tol * scale) & (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol) & (t > 0)
    return torch.where(hit, t, torch.inf)


def _keep_nearest(best: torch.Tensor, face: torch.Tensor, ray, t, f) -> None:
    """Fold candidate hits (ray, t, face), each (M,), into the running nearest ``best`` / ``face`` (R,) in
    place; of equally near faces in one batch the lowest index wins (the same answer on every device)."""
    near = torch.full_like(best, torch.inf).scatter_reduce(0, ray, t, "amin")
    win = (t == near[ray]) & (near[ray] < best[ray])
    none = torch.iinfo(torch.int64).max
    # losers carry `none` rather than being dropped: no compaction, so no wait for its size on a GPU
    pick = torch.full_like(face, none).scatter_reduce(0, ray, torch.where(win, f, none), "amin")
    face.copy_(torch.where(pick != none, pick, face))
    torch.minimum(best, near, out=best)


def _test_leaves(tree, o, d, tri, tol, best, face, ray, leaf) -> None:
    """Test every face of the (ray, leaf) pairs (M,), folding hits into ``best`` / ``face``."""
    slot = tree.members[leaf]
    ray = ray[:, None].expand_as(slot)[slot >= 0]
    f = slot[slot >= 0]
    for p in range(0, len(f), _CHUNK_PAIRS):
        r, fp = ray[p : p + _CHUNK_PAIRS], f[p : p + _CHUNK_PAIRS]
        _keep_nearest(best, face, r, _confirm(o[r], d[r], tri[fp], tol), fp)


@torch.no_grad()
def _bins(tri, o, d) -> pencil.Bins | None:
    """The faces binned for a camera's rays: a pinhole's (one origin) or an orthographic one's (one direction)."""
    if pencil.shared_origin(o):
        return pencil.bin_faces(tri, o[0], d)
    if pencil.shared_direction(d):
        return pencil.bin_faces_parallel(tri, o, d[0])
    return None


def _search_torch(vertices, faces, origins, dirs) -> torch.Tensor:
    """(R,) first-hit face (-1: none), each candidate pair decided by the direct Möller–Trumbore
    (:func:`_confirm`) in float64 where the device has it. Rays that leave one point or share one direction
    (a camera's) take their candidates from faces binned in their image (:mod:`delta.geometry.pencil`); others walk a box
    hierarchy of the faces (:mod:`delta.geometry.clusters`). Tensor work on the inputs' device."""
    work = torch.float64 if vertices.device.type != "mps" else torch.float32
    o, d = origins.detach().to(work), dirs.detach().to(work)
    R, F = o.shape[0], faces.shape[0]
    face = torch.full((R,), -1, dtype=torch.int64, device=o.device)
    if R == 0 or F == 0:
        return face
    tri = vertices.detach().to(work)[faces]
    tol = 64 * torch.finfo(work).eps
    best = torch.full((R,), torch.inf, dtype=work, device=o.device)
    bins = _bins(tri, o, d)
    if bins is not None:  # a camera's rays: each ray's candidates from its cell, no walk
        for ray, f in bins.pairs(_CHUNK_PAIRS):
            _keep_nearest(best, face, ray, _confirm(o[ray], d[ray], tri[f], tol), f)
        return face
    tree = _HIERARCHIES.get(vertices, faces, lambda: clusters.build(tri.amin(1), tri.amax(1), leaf=FACE_LEAF))
    # boxes grown by far more than the slab test's rounding, so no true hit is dropped before _confirm
    scale = tri.abs().amax() + o.abs().amax() + (tri.amax((0, 1)) - tri.amin((0, 1))).amax()
    pad = float(torch.finfo(work).eps ** 0.5 * scale)
    for s in range(0, R, _CHUNK_RAYS):
        ray, leaf, enter = clusters.ray_leaf_pairs(tree, o[s : s + _CHUNK_RAYS], d[s : s + _CHUNK_RAYS], pad)
        ray = ray + s
        # each ray's leaves nearest-entered first, in rounds of 1, 2, 4, ... leaves; a leaf entered beyond
        # the ray's nearest hit so far cannot hold a nearer one and is skipped
        by_enter = torch.argsort(enter, stable=True)
        order = by_enter[torch.argsort(ray[by_enter], stable=True)]
        ray, leaf, enter = ray[order], leaf[order], enter[order]
        rank = clusters.group_rank(ray - s, min(_CHUNK_RAYS, R - s))[1]
        lo, deepest = 0, int(rank.max()) if len(rank) else -1
        while lo <= deepest:
            now = (rank >= lo) & (rank < 2 * lo + 1) & (enter <= best[ray])
            _test_leaves(tree, o, d, tri, tol, best, face, ray[now], leaf[now])
            lo = 2 * lo + 1
    return face


class _MeshCache:
    """What was built for the last mesh cast against (an Embree scene, a face hierarchy), reused while the
    same vertex and face tensors (the same objects, unmodified: their ``_version`` unchanged) come back: a
    whole-image render casts its rays in chunks against one posed mesh. Weak references: a freed tensor
    never matches a new one that reuses its memory."""

    def __init__(self):
        self.key, self.value = None, None

    def holds(self, vertices: torch.Tensor, faces: torch.Tensor) -> bool:
        if self.key is None:
            return False
        v_ref, v_ver, f_ref, f_ver = self.key
        return v_ref() is vertices and f_ref() is faces and v_ver == vertices._version and f_ver == faces._version

    def get(self, vertices: torch.Tensor, faces: torch.Tensor, build: Callable[[], object]):
        if self.holds(vertices, faces):
            return self.value
        self.value = build()
        self.key = (weakref.ref(vertices), vertices._version, weakref.ref(faces), faces._version)
        return self.value


def _embree_scene(vertices, faces):
    """An Embree scene of the mesh, moved to the origin and scaled to a unit box (float32 keeps its
    precision where the mesh is), with the transform to apply to ray origins."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    v = vertices.detach().cpu().double().numpy()
    origin = v.min(0)
    scale = 1.0 / max(float(np.ptp(v, axis=0).max()), 1e-12)
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene=scene, vertices=((v - origin) * scale).astype(np.float32),
                 indices=faces.detach().cpu().numpy().astype(np.int32))  # fmt: skip
    return scene, origin, scale


_SCENES = _MeshCache()
_HIERARCHIES = _MeshCache()


def _search_embree(vertices, faces, origins, dirs) -> torch.Tensor:
    """(R,) first-hit face from Embree (float32 internally; -1: none)."""
    R = origins.shape[0]
    if not R or not faces.shape[0]:
        return torch.full((R,), -1, dtype=torch.int64, device=origins.device)
    scene, origin, scale = _SCENES.get(vertices, faces, lambda: _embree_scene(vertices, faces))
    o = (origins.detach().cpu().double().numpy() - origin) * scale
    d = dirs.detach().cpu().double().numpy()
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    face = scene.run(o.astype(np.float32), d.astype(np.float32))
    return torch.from_numpy(np.asarray(face, dtype=np.int64)).to(origins.device)


TORCH_RAYS = 16384
"""A camera's rays up to this many (a training step's), cast against a mesh Embree has no scene of, are
searched in torch: on two CPU cores Embree's scene of a 110k-face body takes 0.14-0.18 s to build and query,
the binned torch search of 128-12288 rays 0.05-0.10 s in all, of 16384 0.13-0.14 s. Beyond it (24k rays:
0.17-0.19 s in torch), and against a mesh already built, Embree's queries are the faster (32k rays: 0.01 s
against 0.2 s): a whole image's chunks of :data:`delta.models.image.CPU_CHUNK` rays build the scene once.
``benchmarks/ray_casting.py`` measures both."""


def keep_scene(vertices: torch.Tensor, faces: torch.Tensor) -> None:
    """Build Embree's scene of a mesh that many chunks of rays will be cast against (a whole image), where
    ``auto`` would use Embree for a built scene: each chunk, however few its rays, then queries it instead of
    searching the mesh in torch (0.002 s a chunk of 8192 rays against 0.05 s). Nothing on a GPU or without Embree."""
    if host_paths(vertices.device) and embree_available() and faces.shape[0]:
        _SCENES.get(vertices, faces, lambda: _embree_scene(vertices, faces))


def _auto_backend(vertices, faces, origins, dirs) -> str:
    if not host_paths(vertices.device) or not embree_available():
        return "torch"
    if _SCENES.holds(vertices, faces) or origins.shape[0] > TORCH_RAYS:
        return "embree"
    return "torch" if pencil.shared_origin(origins) or pencil.shared_direction(dirs) else "embree"


def ray_mesh_hits(vertices, faces, origins, dirs, backend: str = "auto") -> RayHits:
    """First hit of each ray on a triangle mesh, differentiable in t and barycentrics.

    Args:
        vertices: (V, 3) float, may require grad.
        faces: (F, 3) int64.
        origins: (R, 3) ray origins; dirs: (R, 3) directions (any non-zero length;
            t is measured in units of |dir|).
        backend: "embree" (CPU), "torch" (a box hierarchy walked with tensor operations on the
            inputs' device) or "auto" (torch off the CPU or without Embree; on the CPU, a camera's
            rays against a mesh Embree has not built, up to :data:`TORCH_RAYS` of them, in torch, the rest
            in Embree).
    Returns:
        :class:`RayHits`. Barycentrics are clamped to [0, 1] and renormalised,
        which only changes rays through an edge or vertex (rounding); t is the
        exact hit on the found face's plane in the inputs' precision.
    """
    if backend == "auto":
        backend = _auto_backend(vertices, faces, origins, dirs)
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
