"""The fit's silhouette term: a coarse body mesh, soft-rasterised at low resolution, against the person mask.

The upsampled body mesh (55k vertices) is far finer than a 64-128 px mask needs, so
the term skins a coarse mesh: the base mesh of an upsampled model (its vertices
embed as themselves), decimated by vertex clustering into cells of ``cell`` metres.
Every coarse vertex is a vertex of the model, so it poses with the model's own
skinning weights. All frames are rasterised in one ``soft_silhouette`` call by
placing frame f's image at u-offset f * (size + gap) on one wide canvas.

Shapes: F frames, V coarse vertices, T coarse faces, r the mask resolution.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from delta.body.model import BodyModel
from delta.render.silhouette import soft_silhouette


@dataclasses.dataclass
class CoarseMesh:
    vertex_ids: torch.Tensor
    """(V,) int64 model vertices the coarse mesh keeps."""
    faces: torch.Tensor
    """(T, 3) int64 triangles over ``vertex_ids`` (indices 0..V-1)."""


def base_mesh(model: BodyModel) -> tuple[np.ndarray, np.ndarray]:
    """(N,) base-mesh vertex ids and (T, 3) base faces over model vertex ids; the model's own mesh if not upsampled.

    An upsampled vertex lies in one base triangle; the base vertices that a fine face's
    corners depend on are that triangle's corners, so fine faces depending on three
    distinct base vertices give back the base faces (orientation is irrelevant here).
    """
    faces = model.faces.numpy()
    if model.embed_bary is None:
        return np.arange(model.num_vertices), faces
    ids = np.where(model.embed_bary.numpy() > 0, model.embed_vertex_ids.numpy(), -1)  # (V', 3)
    support = ids[faces].reshape(len(faces), 9)
    support.sort(1)
    first = (support >= 0) & np.concatenate([np.ones((len(faces), 1), bool), support[:, 1:] != support[:, :-1]], 1)
    three = first.sum(1) == 3
    tri = np.unique(support[three][first[three]].reshape(-1, 3), axis=0)
    return np.unique(tri), tri


def coarse_mesh(model: BodyModel, cell: float = 0.03) -> CoarseMesh:
    """The base mesh decimated by vertex clustering on a ``cell``-sized grid (rest pose, mean shape).

    Each occupied cell keeps the vertex nearest its vertices' mean; faces whose corners fall in
    fewer than three cells are dropped. ``cell <= 0`` keeps the base mesh.
    """
    vids, faces = base_mesh(model)
    if cell > 0:
        pts = model.v_template.detach().double().numpy()[vids]
        keys = np.floor(pts / cell).astype(np.int64)
        _, cluster = np.unique(keys, axis=0, return_inverse=True)
        cluster = cluster.reshape(-1)
        n = cluster.max() + 1
        mean = np.zeros((n, 3))
        np.add.at(mean, cluster, pts)
        mean /= np.bincount(cluster, minlength=n)[:, None]
        dist = np.linalg.norm(pts - mean[cluster], axis=1)
        order = np.lexsort((dist, cluster))  # per cluster, nearest first
        first = order[np.concatenate([[True], cluster[order][1:] != cluster[order][:-1]])]
        rep = vids[first]  # representative model vertex of each cluster
        lookup = np.full(model.num_vertices, -1, dtype=np.int64)
        lookup[vids] = cluster
        f = lookup[faces]
        keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
        f = np.unique(np.sort(f[keep], 1), axis=0)
        vids, faces = rep, f
    else:
        remap = np.full(model.num_vertices, -1, dtype=np.int64)
        remap[vids] = np.arange(len(vids))
        faces = remap[faces]
    return CoarseMesh(torch.from_numpy(np.asarray(vids, dtype=np.int64)), torch.from_numpy(faces))


def downsample_masks(masks: np.ndarray | torch.Tensor, size: int) -> torch.Tensor:
    """(F, H, W) masks (uint8 0-255, 0/1 or float) -> (F, size, size) float64 coverage in [0, 1] (area average)."""
    m = torch.as_tensor(np.asarray(masks)).double()
    if m.numel() and m.max() > 1:
        m = m / 255.0
    return torch.nn.functional.adaptive_avg_pool2d(m[:, None], size)[:, 0]


def pixel_grid(size: int, image_size: tuple[int, int], dtype=torch.float64) -> torch.Tensor:
    """(size², 2) centres of a size x size grid over a W x H image, in image pixels (row-major)."""
    W, H = image_size
    u = (torch.arange(size, dtype=dtype) + 0.5) * W / size
    v = (torch.arange(size, dtype=dtype) + 0.5) * H / size
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu.reshape(-1), vv.reshape(-1)], -1)


def _active_pixels(g: torch.Tensor, grid: torch.Tensor, masks: torch.Tensor | None, margin: float) -> torch.Tensor:
    """(F, r²) bool: grid pixels inside the box around frame f's projected vertices and its mask (others cover 0)."""
    lo, hi = g.detach().amin(1), g.detach().amax(1)  # (F, 2)
    if masks is not None:
        size = masks.shape[-1]
        on = masks.reshape(masks.shape[0], -1) > 0
        big = torch.tensor(float(size) * 4, dtype=g.dtype)
        lo = torch.minimum(lo, torch.where(on[..., None], grid[None], big).amin(1))
        hi = torch.maximum(hi, torch.where(on[..., None], grid[None], -big).amax(1))
    return ((grid[None] >= lo[:, None] - margin) & (grid[None] <= hi[:, None] + margin)).all(-1)


def frames_silhouette(uv: torch.Tensor, faces: torch.Tensor, size: int, image_size: tuple[int, int],
                      sigma: float = 0.05, k: int = 8, masks: torch.Tensor | None = None,
                      supersample: int = 1) -> torch.Tensor:  # fmt: skip
    """Soft silhouettes (F, size, size) of F projected meshes uv (F, V, 2) in one batched call.

    ``supersample`` s > 1 renders s x s points a pixel (``sigma`` then in those finer pixels) and
    averages them: the pixel's covered area, as ``downsample_masks`` gives the masks' (one point a
    pixel is all or nothing across a limb thinner than a pixel and biases the fitted size).

    uv is rescaled to the grid (one unit a grid pixel); ``sigma`` is in grid pixels².
    Frames sit side by side on a canvas, 4 ``size`` apart, so no frame's triangles are
    candidates for another frame's pixels (vertices far outside the image are clamped
    to [-size, 2 size] first, which keeps each frame in its own strip). Only pixels in
    the box around a frame's vertices (and its ``masks`` (F, size, size), when given) are
    evaluated; the rest are 0 (they lie farther than a pixel from every triangle).
    """
    if supersample > 1:
        fine = None if masks is None else masks.repeat_interleave(supersample, -1).repeat_interleave(supersample, -2)
        out = frames_silhouette(uv, faces, size * supersample, image_size, sigma, k, fine)
        return torch.nn.functional.avg_pool2d(out[:, None], supersample)[:, 0]
    F, V = uv.shape[:2]
    W, H = image_size
    g = (uv * torch.tensor([size / W, size / H], dtype=uv.dtype)).clamp(-size, 2 * size)
    offset = torch.arange(F, dtype=uv.dtype) * (4 * size)
    canvas = torch.stack([g[..., 0] + offset[:, None], g[..., 1]], -1).reshape(F * V, 2)
    # a triangle whose box misses the grid (and its margin) covers none of its pixels: leave it out. A body
    # mostly outside the image (a head-and-shoulders capture) would otherwise pile thousands of clamped
    # triangles onto the strip's edge, where the nearest-centroid search slows to a crawl
    corners = g.detach()[:, faces]  # (F, T, 3, 2)
    near = ((corners.amax(2) >= -2.0) & (corners.amin(2) <= size + 2.0)).all(-1)  # (F, T)
    all_faces = (faces[None] + V * torch.arange(F)[:, None, None])[near]
    grid = pixel_grid(size, (size, size), uv.dtype)  # (r², 2)
    active = _active_pixels(g, grid, masks, margin=2.0)
    frame, pix = torch.nonzero(active, as_tuple=True)
    pixels = grid[pix] + torch.stack([offset[frame], torch.zeros_like(offset[frame])], -1)
    cover = soft_silhouette(canvas.float(), all_faces, pixels.float(), sigma=sigma, k=k)  # float32: twice as fast
    out = uv.new_zeros(F, size * size).index_put((frame, pix), cover.to(uv.dtype))
    return out.reshape(F, size, size)


def outline_offset(uv: torch.Tensor, faces: torch.Tensor, image: int, size: int, sigma: float,
                   supersample: int = 1) -> torch.Tensor:  # fmt: skip
    """(F,) how far the soft silhouette of (F, V, 2) projected meshes on an ``image`` x ``image`` frame stands
    outside their hard outline, in grid pixels of ``size``: the mesh drawn hard at the image's pixels and
    area-averaged to the grid (as the masks are) is subtracted from its soft drawing (``frames_silhouette`` at
    ``sigma``, ``supersample``), and the excess area divided by the outline's length (the hard drawing's
    boundary pixels, scaled to the grid). Where several triangles lie along the outline, joining them as
    1 - prod(1 - p) covers pixels outside it (docs/fitting.md)."""
    hard = (frames_silhouette(uv, faces, image, (image, image), sigma=1e-4) > 0.5).double()
    mask = downsample_masks(hard, size)
    eroded = -torch.nn.functional.max_pool2d(-hard[:, None], 3, 1, 1)[:, 0]
    length = (hard - eroded).flatten(1).sum(-1) * size / image
    soft = frames_silhouette(uv, faces, size, (image, image), sigma=sigma, masks=mask, supersample=supersample)
    return (soft - mask).flatten(1).sum(-1) / length


def silhouette_term(rendered: torch.Tensor, masks: torch.Tensor, fill: float | torch.Tensor = 1.0,
                    scale: float | torch.Tensor = 1.0) -> torch.Tensor:  # fmt: skip
    """(F,) mean squared coverage error per frame: model outside the mask costs 1, mask left uncovered ``fill``,
    both times ``scale``.

    ``fill`` is a number or a per-pixel (F, r, r) weight (``fill_weights``): below 1 it tolerates
    loose clothing and hair, which the person mask includes and the body mesh does not. ``scale`` is a
    number or a per-pixel (F, r, r) weight on both (``skin_edge_scale``).
    """
    diff = rendered - masks
    fill = torch.as_tensor(fill, dtype=diff.dtype).expand_as(diff)
    w = torch.where(diff > 0, torch.ones_like(diff), fill)
    return (w * torch.as_tensor(scale, dtype=diff.dtype) * diff.square()).flatten(1).mean(-1)


def skin_edge_scale(person: torch.Tensor, exterior: torch.Tensor | None, weight: float) -> torch.Tensor | float:
    """Per-pixel weight (F, r, r): ``weight`` on the grid pixels within one pixel of the visible skin (coverage
    of the person less the exterior over a half), 1 elsewhere; just ``weight`` without an exterior mask (all
    of the person is then body). 1: a plain 1."""
    if weight == 1.0:
        return 1.0
    if exterior is None:
        return float(weight)
    skin = ((person - exterior).clamp_min(0.0) > 0.5).double()
    near = torch.nn.functional.max_pool2d(skin[:, None], 3, stride=1, padding=1)[:, 0] > 0
    return torch.where(near, torch.full_like(person, float(weight)), torch.ones_like(person))


def fill_weights(exterior: torch.Tensor | None, fill: float, exterior_fill: float) -> torch.Tensor | float:
    """Per-pixel weight of mask pixels the body leaves uncovered: ``exterior_fill`` on exterior (clothing, hair)
    coverage (F, r, r) in [0, 1], ``fill`` elsewhere; just ``fill`` without an exterior mask."""
    if exterior is None:
        return fill
    return fill + (exterior_fill - fill) * exterior


def soft_iou(rendered: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """(F,) intersection over union of (F, r, r) coverages (hard masks give the usual IoU); 1 when both are empty."""
    inter = (rendered * masks).flatten(1).sum(-1)
    union = (rendered + masks - rendered * masks).flatten(1).sum(-1)
    return torch.where(union > 0, inter / union.clamp_min(1e-12), torch.ones_like(union))
