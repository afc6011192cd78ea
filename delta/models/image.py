"""Whole images of an avatar: the pixel grid of a frame and a full-frame render, for training's previews,
evaluation and export alike.

These live with the model, not in ``delta.render``: :func:`render_image` renders a
:class:`~delta.models.avatar.HybridAvatar` (its posed mesh, its ``render``, its render settings), and
``delta.render`` sits below ``delta.models`` (the avatar is built from the renderer's pieces), so it
may not import the avatar (``tests/test_layers.py``).

An image is the model's own n×n crop by default, or any :class:`View` of the frame: the capture's
whole frame at its scoring size (evaluation, exports) is one whose pixels map linearly onto the crop's.
"""

from __future__ import annotations

import dataclasses
import itertools

import torch
import torch.nn.functional as F

from delta.data.frames import FullFrames
from delta.devices import host_paths
from delta.geometry.raymesh import keep_scene
from delta.models.avatar import HybridAvatar
from delta.render.hybrid import room_margin


@dataclasses.dataclass(frozen=True)
class View:
    """A height×width image of a frame whose pixel coordinates (u, v) are the model's
    (u·scale[0] + shift[0], v·scale[1] + shift[1]) (pixel centres at +0.5 in both)."""

    height: int
    width: int
    scale: tuple[float, float] = (1.0, 1.0)
    shift: tuple[float, float] = (0.0, 0.0)

    def to_model(self, pixels: torch.Tensor) -> torch.Tensor:
        """(R, 2) view pixel coordinates -> the model's."""
        scale = torch.tensor(self.scale, dtype=pixels.dtype, device=pixels.device)
        return pixels * scale + torch.tensor(self.shift, dtype=pixels.dtype, device=pixels.device)

    def from_model(self, pixels: torch.Tensor) -> torch.Tensor:
        scale = torch.tensor(self.scale, dtype=pixels.dtype, device=pixels.device)
        return (pixels - torch.tensor(self.shift, dtype=pixels.dtype, device=pixels.device)) / scale


def full_view(full: FullFrames, n: int) -> View:
    """The view of a record's whole frames (at their scoring size) for an avatar rendering n×n crops."""
    scale, shift = full.view_geometry(n)
    W, H = full.size
    return View(H, W, scale, shift)


def pixel_grid(n: int, supersample: int = 1, device=None, width: int | None = None) -> torch.Tensor:
    """(n·w·s², 2) ray positions (u, v) of an n-row, w-column image (w = n unless given): an s×s grid
    of sub-pixel centres in each pixel, pixels row-major.

    s = 1 gives the pixel centres. Averaging the s² renders of a pixel is the area average a
    downsampled photograph holds (its edge pixels mix person and background).
    """
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {s}")
    w = n if width is None else int(width)
    sub = (torch.arange(s, dtype=torch.float32) + 0.5) / s
    jj, ii = torch.meshgrid(torch.arange(w, dtype=torch.float32), torch.arange(n, dtype=torch.float32), indexing="xy")
    du, dv = torch.meshgrid(sub, sub, indexing="xy")
    u = jj.reshape(-1, 1) + du.reshape(1, -1)
    v = ii.reshape(-1, 1) + dv.reshape(1, -1)
    return torch.stack([u.reshape(-1), v.reshape(-1)], -1).to(device)


@torch.no_grad()
def reach_box(model: HybridAvatar, frame: int, vertices: torch.Tensor) -> torch.Tensor | None:
    """(4,) (u_min, u_max, v_min, v_max) in the model's pixels bounding everything a ray of the frame
    can meet: the posed mesh's box, grown by the exterior's margin when there is a NeRF. None when
    a corner lies behind a pinhole camera (no bound then)."""
    rs = model.spec.render  # the exterior's samples lie within max_dist (+ the probes' cell) of the body
    margin = (
        min(room_margin(rs.box_margin, rs.max_dist), rs.max_dist + 2 * rs.probe_cell) if model.nerf is not None else 0.0
    )
    lo, hi = vertices.amin(0) - margin, vertices.amax(0) + margin
    corners = torch.stack([torch.stack([(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]])
                           for i, j, k in itertools.product((0, 1), repeat=3)])  # fmt: skip
    uv, depth = model.camera(frame).project(corners)
    if model.pinhole and bool((depth <= 0).any()):
        return None
    return torch.stack([uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()])


def live_rays(pixels: torch.Tensor, box: torch.Tensor | None) -> torch.Tensor:
    """(R,) bool: ray positions (model pixels) inside the reach box (with a pixel to spare)."""
    if box is None:
        return torch.ones(len(pixels), dtype=torch.bool, device=pixels.device)
    u, v = pixels[:, 0], pixels[:, 1]
    return (u >= box[0] - 1) & (u <= box[1] + 1) & (v >= box[2] - 1) & (v <= box[3] + 1)


#: rays a whole-image render casts at once on the CPU; a GPU takes 8x as many (large batches keep it busy)
CPU_CHUNK = 8192
#: supersampling renders the s² rays only of pixels where the image changes by more than this from a
#: neighbouring pixel's centre (in colour or in any mask); elsewhere the pixel's centre stands for them
EDGE = 1 / 64


@torch.no_grad()
def render_image(model: HybridAvatar, frame: int, chunk: int | None = None, supersample: int = 1,
                 view: View | None = None, soft_silhouette: bool = True, edge: float | None = EDGE) -> dict[str, torch.Tensor]:  # fmt: skip
    """Composite, mesh-only, NeRF-only images, NeRF mask and silhouette, (H, W, ·) each; with an exterior
    in layers also each layer's opacity (``layer_clothing``, ``layer_hair``).

    The image is the model's n×n crop, or ``view``. ``supersample`` s averages s² rays a pixel
    (anti-aliased edges) where the pixel's centre differs by more than ``edge`` from a neighbour's
    (:func:`busy_pixels`); elsewhere the image is smooth and its centre ray is the average to second
    order. ``edge`` None: s² rays in every pixel. Rays outside the projection of the box that holds the
    posed mesh and the exterior's reach meet nothing: they get the background without being cast.
    ``soft_silhouette`` False: the silhouette is the mesh hits' coverage (cheaper; no soft edges).
    """
    view = view or View(model.resolution, model.resolution)
    H, W, s = view.height, view.width, int(supersample)
    mesh = model.posed_mesh(frame)[0]
    keep_scene(mesh.vertices, mesh.faces)  # the image's chunks all query one scene
    dev = model.background.device

    def rays(pixels: torch.Tensor) -> dict[str, torch.Tensor]:
        return _render_pixels(model, frame, mesh, view.to_model(pixels), chunk, soft_silhouette)

    if s == 1 or edge is None:
        out = {k: x.reshape(H * W, s * s, -1).mean(1) for k, x in rays(pixel_grid(H, s, dev, width=W)).items()}
    else:
        out = rays(pixel_grid(H, 1, dev, width=W))
        busy = torch.nonzero(busy_pixels(out, H, W, edge)).squeeze(1)
        if len(busy):
            sub = pixel_grid(H, s, dev, width=W).view(H * W, s * s, 2)[busy].reshape(-1, 2)
            for k, x in rays(sub).items():
                out[k][busy] = x.reshape(len(busy), s * s, -1).mean(1).view_as(out[k][busy])
    return {k: x.reshape(H, W, -1).squeeze(-1).cpu() for k, x in out.items()}


def busy_pixels(image: dict[str, torch.Tensor], height: int, width: int, edge: float) -> torch.Tensor:
    """(H·W,) bool: pixels whose value in any of ``image``'s (H·W, C) channels differs by more than ``edge``
    from one of its 8 neighbours'."""
    flat = torch.cat([x.reshape(height * width, -1).float() for x in image.values()], 1)
    grid = flat.T.reshape(1, -1, height, width)
    # the largest difference to a neighbour: max over the 3x3 window of |x - centre|, per channel
    hi = F.max_pool2d(grid, 3, stride=1, padding=1)
    lo = -F.max_pool2d(-grid, 3, stride=1, padding=1)
    spread = torch.maximum(hi - grid, grid - lo).amax(1)[0]
    return (spread > edge).reshape(-1)


def _render_pixels(model: HybridAvatar, frame: int, mesh, pixels: torch.Tensor, chunk: int | None,
                   soft_silhouette: bool) -> dict[str, torch.Tensor]:  # fmt: skip
    """Every image of :func:`render_image` at ray positions (R, 2) (the model's pixels): (R, C) each."""
    dev = model.background.device
    chunk = chunk or (CPU_CHUNK if host_paths(dev) else 8 * CPU_CHUNK)
    live = torch.nonzero(live_rays(pixels, reach_box(model, frame, mesh.vertices))).squeeze(1)
    bg = model.background
    full = {"rgb": bg.expand(len(pixels), 3), "mesh": bg.expand(len(pixels), 3), "nerf": bg.expand(len(pixels), 3),
            "nerf_mask": bg.new_zeros(len(pixels)), "silhouette": bg.new_zeros(len(pixels))}  # fmt: skip
    full |= {f"layer_{n}": bg.new_zeros(len(pixels)) for n in getattr(model.nerf, "names", ())}
    full = {k: v.clone() for k, v in full.items()}
    perturb = model.spec.render.perturb
    model.spec.render.perturb = False
    try:
        for s in range(0, len(live), chunk):
            idx = live[s : s + chunk]
            r = model.render(frame, pixels[idx], mesh=mesh, soft=soft_silhouette)
            layers = r.layer_masks.unbind(1) if r.layer_masks is not None else ()
            for k, v in zip(full, (r.rgb, r.mesh_rgb, r.nerf_rgb, r.nerf_mask, r.silhouette, *layers)):
                full[k][idx] = v.to(full[k].dtype)
    finally:
        model.spec.render.perturb = perturb
    return full
