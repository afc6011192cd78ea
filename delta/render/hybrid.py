"""Render a batch of rays through the hybrid avatar: body mesh + canonical NeRF.

The recipe (R rays, S samples per ray, V vertices): ray–mesh hits -> mesh colour and
soft silhouette -> samples on [t_n, t_f] inside the body's box, t_f at the mesh ->
early cull from the per-frame distance grid (far from the body, or a rough canonical point in
an empty occupancy cell: no kNN query) -> backward skinning (invalid samples cost nothing) ->
optional occupancy test in the canonical space (samples in empty cells cost nothing more) ->
optional non-rigid offsets -> NeRF -> mesh-integrated compositing.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional

import torch

from delta.deformers import knn as deformer
from delta.geometry import distance_grid
from delta.geometry.raymesh import interpolate, ray_mesh_hits
from delta.render.settings import RenderSettings
from delta.render.silhouette import soft_silhouette
from delta.render.volume import composite, distortion, ray_box, sample_deltas, shell_ramp, stratified_samples


@dataclasses.dataclass
class PosedMesh:
    """The interior for one frame."""

    vertices: torch.Tensor
    """(V, 3) posed vertices."""
    faces: torch.Tensor
    """(F, 3)."""
    albedo: torch.Tensor
    """(V, 3) vertex colours."""
    uv: torch.Tensor
    """(V, 2) projected vertices in pixels (for the soft silhouette)."""
    skinning: Optional[deformer.SkinningFrame]
    """Backward-skinning data (None when there is no exterior)."""
    mirror: Optional[Callable[[torch.Tensor], torch.Tensor]] = None
    """Canonical points (N, 3) -> where the exterior is read for them: the mirror image through the body where
    no training frame looked (``delta.models.unseen.exterior_mirror``); None: where they are."""


@dataclasses.dataclass
class RayRender:
    rgb: torch.Tensor
    """(R, 3) composite colour."""
    nerf_mask: torch.Tensor
    """(R,) NeRF opacity s_v."""
    nerf_rgb: torch.Tensor
    """(R, 3) NeRF colour accumulated over the background (the 'NeRF only' view)."""
    mesh_rgb: torch.Tensor
    """(R, 3) mesh colour (background where the ray misses)."""
    hit: torch.Tensor
    """(R,) bool: the ray hits the mesh."""
    silhouette: torch.Tensor
    """(R,) soft mesh coverage, differentiable wrt vertices."""
    samples_evaluated: int
    """NeRF queries made (after culling)."""
    layer_masks: Optional[torch.Tensor] = None
    """(R, L) each exterior layer's opacity (a layered NeRF: the ray's weights times the layer's share
    of the density; they sum to ``nerf_mask``), None for one NeRF."""
    layer_depths: Optional[torch.Tensor] = None
    """(R, L) where along the ray each layer is seen: the depth t of its opacity's weighted mean
    Σ_k w_k (σ_l,k / σ_k) t_k / S_l (the far bound where the layer has no opacity; not differentiated),
    None for one NeRF."""
    optical_depth: Optional[torch.Tensor] = None
    """(R,) the exterior's optical depth τ = Σ σ_k Δ_k along the ray (``nerf_mask`` = 1 - e^-τ), None
    without an exterior."""
    shell_depth: Optional[torch.Tensor] = None
    """(R,) the optical depth beyond the soft shell, Σ σ_k Δ_k r(d_k) with d_k the sample's distance to the
    body and r :func:`delta.render.volume.shell_ramp` (``settings.shell`` > 0; else None)."""
    layer_log_shares: Optional[torch.Tensor] = None
    """(R, S - 1, L) the log of each layer's share σ_l,k / σ_k of a sample's density (0 where the sample has
    none), differentiable where the layer's density is above the dtype's smallest normal (e^-87 in
    float32); None for one NeRF."""
    sample_weights: Optional[torch.Tensor] = None
    """(R, S - 1) each NeRF sample's weight w_k in the ray's colour, not differentiated (a layered NeRF;
    else None)."""
    distortion: Optional[torch.Tensor] = None
    """(R,) how far apart along the ray the exterior's weight lies, in metres (:func:`delta.render.volume.distortion`),
    None without an exterior."""


#: cells the occupied set grows by for the early cull: the rough canonical point lies within 3 cm of
#: the kNN blend's on a trained avatar (99th percentile 0.9 cm), under one 3.2-cm occupancy cell
EARLY_GROW = 1


def room_margin(margin: float, max_dist: float) -> float:
    """A box margin (m) that holds the exterior's room: at least ``max_dist`` where that bounds the
    exterior (culling by distance: ``max_dist`` ≤ ``GRID_REACH``), else ``margin`` alone (the paper's
    10-m room, where the box is the bound). A room decided from the capture (a hem 0.3 m from the legs)
    is then never cut by a box margin set for another scene."""
    return max(margin, max_dist) if max_dist <= distance_grid.GRID_REACH else margin


NeRF = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
Deform = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
Occupied = Callable[[torch.Tensor], torch.Tensor]
"""Canonical points (N, 3) -> (N,) bool: may have density (False: skipped); ``grow`` (keyword):
the same test in the occupied set grown by that many cells; ``settled`` (keyword): the points are
where the NeRF is queried (after F_e), tested against the set without F_e's reach."""


def render_rays(mesh: PosedMesh, origins: torch.Tensor, dirs: torch.Tensor, pixels: torch.Tensor,
                background: torch.Tensor, settings: RenderSettings, nerf: Optional[NeRF] = None,
                nonrigid: Optional[Deform] = None, generator: torch.Generator | None = None,
                occupied: Optional[Occupied] = None, through_mesh: bool = False, soft: bool = True) -> RayRender:  # fmt: skip
    """Render rays (R, 3) through pixels (R, 2) of one frame; ``occupied`` skips samples in empty canonical space.

    ``through_mesh``: the rays do not stop at the mesh (the NeRF alone over the background, SCARF's
    NeRF-only stage); the mesh's colour and silhouette are still returned. ``soft`` False: the
    silhouette is the hits alone (no soft rasterisation: nothing to differentiate, an image to show).
    """
    hits = ray_mesh_hits(mesh.vertices, mesh.faces, origins, dirs)
    mesh_rgb = torch.where(hits.hit[:, None], interpolate(hits, mesh.faces, mesh.albedo), background)
    if soft:
        sil = soft_silhouette(mesh.uv, mesh.faces, pixels, sigma=settings.sil_sigma, k=settings.sil_k)
        if settings.sil_hard_value:
            sil = hits.hit.to(sil.dtype) + (sil - sil.detach())
    else:
        sil = hits.hit.to(mesh_rgb.dtype)
    if nerf is None or mesh.skinning is None:
        zero = torch.zeros_like(sil)
        return RayRender(mesh_rgb, zero, background.expand_as(mesh_rgb), mesh_rgb, hits.hit, sil, 0)
    t = ray_samples(mesh, origins, dirs, hits, settings, through_mesh, generator)
    sigma, rgb, layer_sigma, dist, n = _query(mesh, origins, dirs, t, settings, nerf, nonrigid, occupied)
    shell = None
    if settings.shell > 0:
        shell = (sigma * sample_deltas(t) * shell_ramp(dist, settings.shell, settings.max_dist)).sum(1)
    out = composite(t, sigma, rgb, background.expand_as(mesh_rgb) if through_mesh else mesh_rgb)
    nerf_rgb = (out.weights[:, :-1, None] * rgb).sum(1) + (1 - out.nerf_mask[:, None]) * background
    layer_masks = layer_depths = log_shares = seen_w = None
    if layer_sigma is not None:
        tiny = torch.finfo(sigma.dtype).tiny
        share = layer_sigma / sigma.clamp_min(tiny)[..., None]
        log_shares = layer_sigma.clamp_min(tiny).log() - sigma.clamp_min(tiny).log()[..., None]
        seen_w = out.weights[:, :-1].detach()
        seen = out.weights[:, :-1, None] * share  # (R, S - 1, L)
        layer_masks = seen.sum(1)
        with torch.no_grad():  # a readout: where the layer lies, nothing to differentiate
            at = (seen * t[:, :-1, None]).sum(1) / layer_masks.clamp_min(torch.finfo(t.dtype).tiny)
            layer_depths = torch.where(layer_masks > 0, at, t[:, -1:])
    return RayRender(out.rgb, out.nerf_mask, nerf_rgb, mesh_rgb, hits.hit, sil, n, layer_masks, layer_depths,
                     out.optical_depth, shell, log_shares, seen_w, distortion(t, out.weights))  # fmt: skip


def ray_samples(mesh: PosedMesh, origins, dirs, hits, settings: RenderSettings, through_mesh: bool = False,
                generator: torch.Generator | None = None) -> torch.Tensor:  # fmt: skip
    """(R, S) sample positions along rays (R, 3) inside the body's box and within ``max_dist`` of the body,
    the last at the mesh's hit (``hits``) unless ``through_mesh`` (then at the box's far side)."""
    margin = room_margin(settings.box_margin, settings.max_dist)
    lo = mesh.vertices.detach().amin(0) - margin
    hi = mesh.vertices.detach().amax(0) + margin
    t_in, t_out, in_box = ray_box(origins, dirs, lo, hi)
    stop = hits.hit & (not through_mesh)
    t_far = torch.where(stop, torch.minimum(hits.t, t_out), t_out)
    t_far = torch.where(in_box | stop, t_far, t_in)
    t_near, t_far = body_span(mesh.skinning, origins, dirs, t_in, torch.maximum(t_far, t_in), stop, settings)
    return stratified_samples(t_near, t_far, settings.samples, settings.perturb, generator)


@torch.no_grad()
def exterior_surface(mesh: PosedMesh, origins: torch.Tensor, dirs: torch.Tensor, settings: RenderSettings,
                     nerf: NeRF, nonrigid: Optional[Deform] = None, generator: torch.Generator | None = None,
                     occupied: Optional[Occupied] = None) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Where rays (R, 3) see the exterior: the posed point (R, 3) at the opacity-weighted mean depth of their
    NeRF samples, and the exterior's opacity (R,) (rays stop at the mesh; not differentiated). A ray with
    no exterior opacity gets its origin."""
    hits = ray_mesh_hits(mesh.vertices, mesh.faces, origins, dirs)
    t = ray_samples(mesh, origins, dirs, hits, settings, False, generator)
    sigma, *_ = _query(mesh, origins, dirs, t, settings, nerf, nonrigid, occupied)
    out = composite(t, sigma, sigma.new_zeros(*sigma.shape, 1), sigma.new_zeros(len(t), 1))
    w = out.weights[:, :-1]
    depth = (w * t[:, :-1]).sum(1) / out.nerf_mask.clamp_min(torch.finfo(t.dtype).tiny)
    return origins + depth[:, None] * dirs, out.nerf_mask


@torch.no_grad()
def body_span(skinning, origins, dirs, t_in, t_far, hit, settings: RenderSettings):
    """Shrink [t_in, t_far] to where the ray passes within ``max_dist`` of the body (non-differentiable).

    ``probe`` evenly spaced points are checked against the posed vertices; the span runs from one probe
    spacing before the first close point to one after the last (to t_far for rays ending on the mesh).
    Rays never close to the body get an empty span at t_far: they render the background (or mesh) only.
    """
    n = settings.probe
    u = torch.linspace(0, 1, n, dtype=t_in.dtype, device=t_in.device)
    tp = t_in[:, None] + (t_far - t_in)[:, None] * u
    pts = (origins[:, None] + tp[..., None] * dirs[:, None]).reshape(-1, 3)
    if skinning.near is not None:
        close = distance_grid.lookup(skinning.near, pts) < settings.max_dist
    else:
        close = skinning.index.query(pts, 1)[0][:, 0] < settings.max_dist
    close = close.view(-1, n).to(t_in.device)
    step = (t_far - t_in) / (n - 1)
    idx = torch.arange(n, device=t_in.device).expand_as(close)
    first = torch.where(close, idx, n).amin(1)
    last = torch.where(close, idx, -1).amax(1)
    any_close = last >= 0
    lo = (t_in + (first - 1).clamp_min(0) * step).where(any_close, t_far)
    hi = torch.where(hit, t_far, torch.minimum(t_in + (last + 1) * step, t_far)).where(any_close, t_far)
    return lo, torch.maximum(hi, lo)


def early_cull(skinning: deformer.SkinningFrame, points: torch.Tensor, max_dist: float,
               occupied: Optional[Occupied] = None) -> torch.Tensor:  # fmt: skip
    """(N,) bool: posed points that may pass the exact tests (kNN distance, occupancy), from the
    distance grid alone (no kNN query); needs ``skinning.near``."""
    rough, dist = deformer.rough_canonical(skinning, points)
    keep = dist < max_dist + math.sqrt(3) * skinning.near.cell * (1 + 1e-6)
    if occupied is not None:
        inside = occupied(rough, grow=EARLY_GROW)
        if skinning.touching is not None:  # near a contact the nearest vertex's map is one candidate of two
            inside |= deformer.near_contact(skinning, points)
        keep &= inside
    return keep


#: samples a ray takes at once when rendering without gradients: the rays whose transmittance has
#: fallen below ``OPAQUE`` by then take no more (early ray termination)
MARCH = 16
#: transmittance below which the rest of a ray changes its colour by less than this share (no more samples)
OPAQUE = 1e-4


def _query(mesh: PosedMesh, origins, dirs, t, settings: RenderSettings, nerf: NeRF, nonrigid, occupied=None):
    """Densities and colours of the NeRF samples (all but the last), zero where culled, each layer's
    density (R, S - 1, L) for a layered NeRF (else None), each sample's distance to the body (R, S - 1;
    0 where culled, not differentiated) and the number of samples evaluated.

    Culling, cheapest first: rays with an empty span, the early cull (distance grid and rough
    canonical point), samples beyond ``max_dist`` of the body (kNN), then samples whose canonical
    point is in an empty occupancy cell (before F_e and the NeRF). Without gradients the rays march
    ``MARCH`` samples at a time, and a ray whose transmittance is below ``OPAQUE`` stops: its later
    samples keep σ = 0, which moves its colour by less than ``OPAQUE`` (the mesh or background then
    takes the weight those samples would have had, at most the transmittance left).
    """
    R, S = t.shape
    points = origins[:, None] + t[:, :-1, None] * dirs[:, None]  # (R, S - 1, 3)
    flat = points.reshape(-1, 3)
    layered = hasattr(nerf, "with_layers")
    sigma = flat.new_zeros(R * (S - 1))
    rgb = flat.new_zeros(R * (S - 1), 3)
    dist = flat.new_zeros(R * (S - 1))
    layer_sigma = flat.new_zeros(R * (S - 1), len(nerf.names)) if layered else None
    open_rays = torch.nonzero(t[:, -1] > t[:, 0]).squeeze(1)  # rays with a non-empty interval
    march = S - 1 if torch.is_grad_enabled() else MARCH
    optical = flat.new_zeros(R)  # optical depth so far (-log transmittance)
    evaluated = 0
    for s0 in range(0, S - 1, march):
        s1 = min(s0 + march, S - 1)
        if s0:
            open_rays = open_rays[optical[open_rays] < -math.log(OPAQUE)]
        idx = (open_rays[:, None] * (S - 1) + torch.arange(s0, s1, device=t.device)).reshape(-1)
        at, s, c, s_layers, d = _query_points(mesh, flat, idx, settings, nerf, nonrigid, occupied)
        evaluated += len(at)
        sigma = sigma.index_put((at,), s)
        dist[at] = d
        rgb = rgb.index_put((at,), c)
        if layered:
            layer_sigma = layer_sigma.index_put((at,), s_layers)
        if s1 < S - 1:
            optical = optical + (sigma.view(R, S - 1)[:, s0:s1] * sample_deltas(t[:, s0 : s1 + 1])).sum(1)
    if layered:
        layer_sigma = layer_sigma.view(R, S - 1, -1)
    return sigma.view(R, S - 1), rgb.view(R, S - 1, 3), layer_sigma, dist.view(R, S - 1), evaluated


def _query_points(mesh: PosedMesh, flat, idx, settings: RenderSettings, nerf: NeRF, nonrigid, occupied):
    """The NeRF at posed points ``flat[idx]`` that pass the culls: their indices into ``flat`` (P,),
    densities (P,), colours (P, 3), each layer's density (P, L) (None for one NeRF) and distances to the
    body (P,), detached."""
    layered = hasattr(nerf, "with_layers")
    layers = flat.new_zeros(0, len(nerf.names)) if layered else None
    none = idx[:0], flat.new_zeros(0), flat.new_zeros(0, 3), layers, flat.new_zeros(0)
    if settings.early_cull and mesh.skinning.near is not None and len(idx):
        cull = occupied
        if occupied is not None and mesh.mirror is not None:  # a point is culled by where it is read
            cull = lambda x, **kw: occupied(mesh.mirror(x), **kw)  # noqa: E731
        idx = idx[early_cull(mesh.skinning, flat[idx], settings.max_dist, cull)]
    if not len(idx):
        return none
    d = deformer.deform(mesh.skinning, flat[idx], settings.k, settings.sigma, settings.max_dist)
    x_c, ref, rows = d.canonical, d.posed_ref, torch.arange(len(idx), device=idx.device)
    valid, carrier = d.valid, d.nearest
    if d.other is not None:  # second candidates near surfaces in contact: evaluated beside the first
        x_c, ref = torch.cat([x_c, d.other.canonical]), torch.cat([ref, d.other.posed_ref])
        rows, valid = torch.cat([rows, d.other.rows]), torch.cat([valid, d.other.valid])
        carrier = torch.cat([carrier, d.other.nearest])
    points = [x_c]  # and a hair layer bound to the head its own canonical points (the first candidates')
    if layered and "hair" in nerf.names and mesh.skinning.head_index is not None:
        points.append(torch.cat([deformer.head_bound(mesh.skinning, flat[idx], d.canonical, d.distance),
                                 x_c[len(idx) :]]))  # fmt: skip
    if mesh.mirror is not None:
        points = [mesh.mirror(p) for p in points]
    if occupied is not None:  # a sample stays where any layer's point may have density
        valid = valid & _any_occupied(occupied, points)
    keep = torch.nonzero(valid).squeeze(1)
    points = [p[keep] for p in points]
    if nonrigid is not None and len(keep):
        moved = nonrigid(points[0], ref[keep])
        points = [p + moved for p in points]
        if occupied is not None:  # the test above allowed for F_e's reach; the moved point meets the set itself
            settled = torch.nonzero(_any_occupied(occupied, [p.detach() for p in points], settled=True)).squeeze(1)
            keep, points = keep[settled], [p[settled] for p in points]
    if not len(keep):
        return none
    s_layers = None
    if layered:
        own = ({"hair": points[1]},) if len(points) > 1 else ()  # a layer's own points only where it has them
        c, s, s_layers = nerf.with_layers(points[0], carrier[keep], *own)
    else:
        c, s = nerf(points[0])
    at, pick = rows[keep], slice(None)  # one candidate a point: each is its point's own
    if d.other is not None:
        at, pick = denser(at, s)
    return idx[at], s[pick], c[pick], None if s_layers is None else s_layers[pick], d.distance[at].detach()


def _any_occupied(occupied, points: list[torch.Tensor], **kw) -> torch.Tensor:
    """(N,) bool: any of the candidate canonical points (each (N, 3)) of the same samples is occupied."""
    inside = occupied(points[0], **kw)
    for p in points[1:]:
        inside = inside | occupied(p, **kw)
    return inside


def denser(rows: torch.Tensor, sigma: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Of candidates (M,) for points ``rows`` (M,), the densest of each point: the distinct points (P,) and
    the index (P,) of their candidate (ties: the first listed)."""
    order = torch.argsort(sigma.detach(), descending=True, stable=True)
    at, first = torch.unique(rows[order], return_inverse=True)
    pick = torch.full((len(at),), len(order), dtype=torch.long, device=rows.device)
    pick = pick.scatter_reduce(0, first, torch.arange(len(order), device=rows.device), "amin")
    return at, order[pick]
