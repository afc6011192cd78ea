"""DELTA's objective (paper §3.4) as pure functions, and their weights.

Each term takes tensors over a batch of R rays (or the mesh) and returns a scalar;
the weights multiply them in :func:`total`. Masks are floats in [0, 1]:
``person`` the whole avatar, ``exterior`` clothing or hair, ``interior`` the visible body.
"""

from __future__ import annotations


import torch

from delta.body.model import REGION
from delta.loss_weights import LossWeights


def huber_each(x: torch.Tensor, delta: float = 0.1) -> torch.Tensor:
    """The Huber penalty of each residual of x: x²/2 for |x| ≤ δ, δ(|x| - δ/2) beyond."""
    a = x.abs()
    return torch.where(a <= delta, 0.5 * a * a, delta * (a - 0.5 * delta))


def ray_mean(x: torch.Tensor) -> torch.Tensor:
    """The mean of x, 0 for an empty x (a batch with no such rays; the mean of nothing is NaN)."""
    return x.mean() if x.numel() else x.sum()


def huber(x: torch.Tensor, delta: float = 0.1) -> torch.Tensor:
    """Mean Huber penalty of residuals x (:func:`huber_each`; 0 for an empty x)."""
    return ray_mean(huber_each(x, delta))


def pixel(rgb: torch.Tensor, target: torch.Tensor, delta: float = 0.1) -> torch.Tensor:
    return huber(rgb - target, delta)


def exterior(nerf_mask: torch.Tensor, exterior_mask: torch.Tensor) -> torch.Tensor:
    """‖S_v - S_e‖_1, averaged over rays (0 for no rays, as :func:`huber`)."""
    return ray_mean((nerf_mask - exterior_mask).abs())


def exterior_layers(layer_masks: torch.Tensor, names: tuple[str, ...], exterior_mask: torch.Tensor,
                    hair_mask: torch.Tensor | None) -> torch.Tensor:  # fmt: skip
    """Mean over the layers of ‖S_l - M_l‖_1: the hair layer's opacity against the hair mask, the
    clothing layer's against the rest of the exterior mask (R rays, ``layer_masks`` (R, L))."""
    if hair_mask is None:
        raise ValueError("an exterior in layers needs the hair mask (load the frames with hair=True)")
    return ray_mean((layer_masks - stacked_targets(exterior_mask, hair_mask, names)).abs())


def empty_background(optical_depth: torch.Tensor, person: torch.Tensor) -> torch.Tensor:
    """Mean over rays of β τ: the exterior's optical depth τ = Σ σ_k Δ_k on rays the person mask puts on
    the background, β = clamp(1 - 2 M, 0, 1) (1 on the background, 0 from half the person's alpha on).

    The opacity's terms (:func:`exterior`, :func:`pixel`) reach a sample's density through e^-τ, which
    vanishes once a ray is opaque: density that a moving outline (hair, a hem) put where other frames see
    background stays there, and the exterior's silhouette grows to the union of its frames' outlines.
    τ's gradient, Δ_k, does not vanish (0 for no rays, as :func:`huber`)."""
    return ray_mean((1 - 2 * person).clamp(0.0, 1.0) * optical_depth)


def shell(shell_depth: torch.Tensor) -> torch.Tensor:
    """Mean over rays of the optical depth beyond the soft shell (``RayRender.shell_depth``): where a ray's
    colour does not tell how deep its exterior lies, the density costs least nearest the body
    (0 for no rays, as :func:`huber`)."""
    return ray_mean(shell_depth)


def distortion(spread: torch.Tensor) -> torch.Tensor:
    """Mean over rays of how far apart along each ray the exterior's weight lies (``RayRender.distortion``,
    metres): of the depths that give a ray its colour, the most compact costs least, so an exterior no
    frame sees from the side is drawn as a sheet, not a slab (0 for no rays, as :func:`huber`)."""
    return ray_mean(spread)


def layer_shares(log_shares: torch.Tensor, weights: torch.Tensor, names: tuple[str, ...],
                 exterior_mask: torch.Tensor, hair_mask: torch.Tensor | None) -> torch.Tensor:  # fmt: skip
    """Mean over the exterior's rays of the cross-entropy between the layers' shares of each sample the ray
    sees and its pixel's layers: -Σ_k ŵ_k Σ_l q_l log(σ_l,k / σ_k), ŵ the ray's sample weights (R, S - 1)
    normalised to sum 1 (not differentiated), q its layer masks normalised (the hair mask and the rest
    of the exterior, :func:`layer_targets`), ``log_shares`` (R, S - 1, L) in ``names`` order.

    With densities e^raw a share is a softmax of the raws, and a layer's opacity (:func:`exterior_layers`)
    reaches its raw density through share (1 - share): a layer that another has pushed out of a region
    (share -> 0) gets no gradient there and stays out. This term's gradient at a seen sample's raw
    density is ŵ_k (share - q_l): the lost layer wins its region back. Rays outside the exterior (mask
    under 0.5) and rays that see no density add nothing (0 for none, as :func:`huber`)."""
    if hair_mask is None:
        raise ValueError("an exterior in layers needs the hair mask (load the frames with hair=True)")
    q = stacked_targets(exterior_mask, hair_mask, names)
    total = q.sum(-1)  # 0 only where the names leave out the pixel's layer
    seen = weights.sum(-1)
    rays = (exterior_mask > 0.5) & (total > 0) & (seen > 0)
    if not bool(rays.any()):
        return log_shares.sum() * 0.0
    q = q[rays] / total[rays, None]
    w = weights[rays] / seen[rays, None]
    return -(w[..., None] * q[:, None, :] * log_shares[rays]).sum((1, 2)).mean()


def layer_targets(exterior_mask: torch.Tensor, hair_mask: torch.Tensor) -> dict[str, torch.Tensor]:
    """Each exterior layer's mask: the hair mask, and the rest of the exterior as clothing."""
    return {"hair": hair_mask, "clothing": (exterior_mask - hair_mask).clamp_min(0.0)}


def stacked_targets(exterior_mask: torch.Tensor, hair_mask: torch.Tensor, names: tuple[str, ...]) -> torch.Tensor:
    """(R, L) the layers' masks (:func:`layer_targets`) in ``names`` order."""
    targets = layer_targets(exterior_mask, hair_mask)
    return torch.stack([targets[n] for n in names], -1)


def silhouette(mesh_sil: torch.Tensor, person: torch.Tensor, delta: float = 0.1) -> torch.Tensor:
    return huber(mesh_sil - person, delta)


def interior_mask(mesh_sil: torch.Tensor, interior: torch.Tensor, delta: float = 0.1) -> torch.Tensor:
    """L_δ(M_b ⊙ R_s - M_b): the mesh must cover the visible body."""
    return huber(interior * mesh_sil - interior, delta)


def skin(mesh_rgb: torch.Tensor, target: torch.Tensor, interior: torch.Tensor, delta: float = 0.1) -> torch.Tensor:
    """L_δ(M_b ⊙ (R_m - I)): the mesh colour matches the visible body."""
    return huber(interior[:, None] * (mesh_rgb - target), delta)


def inside(mesh_sil: torch.Tensor, person: torch.Tensor, delta: float = 0.1) -> torch.Tensor:
    """L_δ(ReLU(R_s - M)): the body mesh stays inside the avatar's silhouette."""
    return huber(torch.relu(mesh_sil - person), delta)


def skin_inside(mesh_rgb: torch.Tensor, skin_color: torch.Tensor, exterior_mask: torch.Tensor,
                delta: float = 0.1) -> torch.Tensor:  # fmt: skip
    """L_δ(M_c ⊙ (R_m - C_skin)): occluded body takes the average visible skin colour."""
    return huber(exterior_mask[:, None] * (mesh_rgb - skin_color), delta)


def edge(displacement: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Relative edge loss between a mesh v and its reference u = v - d, from the displacement d (V, 3):
    mean ‖(v_a - v_b) - (u_a - u_b)‖² = mean ‖d_a - d_b‖² over edges (E, 2). Taken from d itself, its
    gradient reaches d alone (through v and u it would cancel, up to rounding, at twice the gathers)."""
    diff = displacement[edges[:, 0]] - displacement[edges[:, 1]]
    return (diff**2).sum(-1).mean()


def offset(offsets: torch.Tensor, regions: torch.Tensor, region_weights: dict) -> torch.Tensor:
    """Σ_v w(region_v) ‖o_v‖² / V."""
    w = torch.ones(len(REGION), dtype=offsets.dtype, device=offsets.device)
    for name, value in region_weights.items():
        w[REGION[name]] = value
    return (w[regions] * (offsets**2).sum(-1)).mean()


FACE_DELTA = 0.01
"""The face points' distance (a fraction of the image's size: 5 px of 512) beyond which it costs linearly."""


def face_points(uv: torch.Tensor, target: torch.Tensor, confidence: torch.Tensor, size: int,
                delta: float = FACE_DELTA) -> torch.Tensor:  # fmt: skip
    """Σ_k c_k h(‖uv_k − t_k‖ / size) / Σ_k c_k, h the Huber penalty (δ ``delta``): (K, 2) projected face
    points against (K, 2) detected ones in pixels, weighted by their (K,) confidences (0 with none)."""
    h = huber_each(torch.linalg.vector_norm(uv - target, dim=-1) / size, delta)
    w = confidence.to(h.dtype)
    return (w * h).sum() / w.sum().clamp_min(torch.finfo(h.dtype).tiny)


#: metres: the track term is √(d² + ε²), a distance that stays smooth where two points meet
TRACK_EPS = 1e-3
#: the exterior opacity both ends of a track need for the term to read it
TRACK_OPACITY = 0.5


def track(start: torch.Tensor, end: torch.Tensor, along_start: torch.Tensor, along_end: torch.Tensor,
          opacity_start: torch.Tensor, opacity_end: torch.Tensor, floor: float = TRACK_OPACITY) -> torch.Tensor:  # fmt: skip
    """Mean distance (metres, √(d² + ε²)) across the rays between the canonical points (M, 3) where the rays
    of a tracked point's two ends see the exterior, over the tracks whose rays are both at least ``floor``
    opaque (their (M,) opacities; 0 where none is). The same point of the cloth should be one canonical point;
    how deep along its ray a ray sees a cloth is the density's to say (a smeared or thick exterior spreads it
    over centimetres), so the component along the rays' mean canonical direction (``along_*``, (M, 3) unit)
    is left out."""
    keep = (torch.minimum(opacity_start, opacity_end) >= floor).detach().to(start.dtype)
    u = torch.nn.functional.normalize(along_start + along_end, dim=-1).detach()
    gap = start - end
    across = gap - (gap * u).sum(-1, keepdim=True) * u
    d = (across**2).sum(-1).add(TRACK_EPS**2).sqrt()
    return (d * keep).sum() / keep.sum().clamp_min(1.0)


def vertex_detail(details: list[torch.Tensor]) -> torch.Tensor:
    """Mean over the given (V, C) per-vertex details of their mean squared value."""
    return sum((d**2).sum(-1).mean() for d in details) / len(details)


def mesh_edges(faces: torch.Tensor) -> torch.Tensor:
    """(F, 3) faces -> (E, 2) unique undirected edges."""
    e = torch.sort(torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), dim=1).values
    n = int(faces.max()) + 1 if len(faces) else 1
    key = torch.unique(e[:, 0] * n + e[:, 1])  # one integer an edge, in the pairs' lexicographic order
    return torch.stack([key // n, key % n], 1)


def total(terms: dict[str, torch.Tensor], weights: LossWeights) -> torch.Tensor:
    """Σ λ_name · term over the terms present (a term missing from ``terms`` costs nothing)."""
    out = None
    for name, value in terms.items():
        part = getattr(weights, name) * value
        out = part if out is None else out + part
    if out is None:
        raise ValueError("no loss terms")
    return out
