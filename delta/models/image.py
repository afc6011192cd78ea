"""Whole images of an avatar: the pixel grid of a frame and a full-frame render, for training's previews,
evaluation and export alike.

These live with the model, not in ``delta.render``: :func:`render_image` renders a
:class:`~delta.models.avatar.HybridAvatar` (its posed mesh, its ``render``, its render settings), and
``delta.render`` sits below ``delta.models`` (the avatar is built from the renderer's pieces), so it
may not import the avatar (``tests/test_layers.py``).
"""

from __future__ import annotations

import torch

from delta.models.avatar import HybridAvatar


def pixel_grid(n: int, supersample: int = 1, device=None) -> torch.Tensor:
    """(n·n·s², 2) ray positions (u, v): an s×s grid of sub-pixel centres in each pixel, pixels row-major.

    s = 1 gives the pixel centres. Averaging the s² renders of a pixel is the area average a
    downsampled photograph holds (its edge pixels mix person and background).
    """
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {s}")
    sub = (torch.arange(s, dtype=torch.float32) + 0.5) / s
    jj, ii = torch.meshgrid(torch.arange(n, dtype=torch.float32), torch.arange(n, dtype=torch.float32), indexing="xy")
    du, dv = torch.meshgrid(sub, sub, indexing="xy")
    u = jj.reshape(-1, 1) + du.reshape(1, -1)
    v = ii.reshape(-1, 1) + dv.reshape(1, -1)
    return torch.stack([u.reshape(-1), v.reshape(-1)], -1).to(device)


@torch.no_grad()
def render_image(model: HybridAvatar, frame: int, chunk: int = 4096, supersample: int = 1) -> dict[str, torch.Tensor]:
    """Full-frame composite, mesh-only, NeRF-only images and NeRF mask, (n, n, ·) each.

    ``supersample`` s renders s² rays a pixel and averages them (anti-aliased edges).
    """
    n, s2 = model.resolution, int(supersample) ** 2
    pixels = pixel_grid(n, supersample, model.background.device)
    mesh = model.posed_mesh(frame)[0]
    perturb = model.spec.render.perturb
    model.spec.render.perturb = False
    parts: dict[str, list] = {"rgb": [], "mesh": [], "nerf": [], "nerf_mask": [], "silhouette": []}
    try:
        for s in range(0, len(pixels), chunk):
            r = model.render(frame, pixels[s : s + chunk], mesh=mesh)
            for k, v in zip(parts, (r.rgb, r.mesh_rgb, r.nerf_rgb, r.nerf_mask, r.silhouette)):
                parts[k].append(v)
    finally:
        model.spec.render.perturb = perturb
    out = {}
    for k, v in parts.items():
        x = torch.cat(v)
        out[k] = x.reshape(n * n, s2, -1).mean(1).reshape(n, n, -1).squeeze(-1).cpu()
    return out
