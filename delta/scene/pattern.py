"""How fine the exterior's pattern is: whether a colour grid of the preset's cells can draw it.

A colour grid of cell ``c`` draws a surface's pattern no finer than its cells: what is left of a frame's
exterior after averaging it over cells of ``c``'s footprint and interpolating linearly between them
(:func:`grid_residual`) is the detail such a grid cannot hold however long it trains. Its PSNR over the
exterior's pixels is the grid's *ceiling* there. A pattern that a grid of the preset's cells draws no
better than :data:`PATTERN_DB` (dots, checks, prints with sharp edges) gets colour cells of
:data:`CELL_PIXELS` training pixels' footprint, the finest the frames resolve; a plain garment or hair
keeps the preset's (no cost where nothing is gained: *model only what a scene requires*).

Pure numpy and OpenCV; the scene analysis (:mod:`delta.scene.analysis`) reads the frames and decides.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

#: The decided colour cell is this many training pixels' footprint at the body: the frames' Nyquist limit
#: (a pattern finer than two pixels is not in them).
CELL_PIXELS = 2.0
#: A pattern that a grid of the preset's colour cells draws no better than this PSNR over the exterior's
#: pixels (an RMS error of 3 % of the range) gets the finer cells. The presets' held-out figures lie at
#: 25-30 dB: a pattern the cells hold no better than that limits the exterior more than the rest does.
PATTERN_DB = 30.0
#: The ceiling reported where nothing is left (a plain exterior drawn exactly).
MAX_DB = 60.0
#: The exterior's mask is eroded by this many pixels before measuring (its outline's pixels mix in what
#: lies next to it, which is not its pattern).
ERODE = 1


def grid_residual(image: np.ndarray, mask: np.ndarray, cell: float) -> np.ndarray:
    """(H, W, C) what a grid of ``cell``-pixel cells cannot draw of ``image`` (H, W, C float) inside ``mask``
    (H, W bool): the image minus its mask-weighted average over cells, interpolated linearly between cell
    centres. Outside the mask the residual is 0, and pixels outside do not enter a cell's average (a
    garment's cells hold the garment, not the skin beside it). ``cell`` < 1 draws everything."""
    if cell <= 1.0 or not mask.any():
        return np.zeros_like(image)
    h, w = mask.shape
    size = (max(1, round(w / cell)), max(1, round(h / cell)))
    m = mask.astype(np.float32)
    num = cv2.resize(image * m[..., None], size, interpolation=cv2.INTER_AREA)
    den = cv2.resize(m, size, interpolation=cv2.INTER_AREA)
    num = cv2.resize(num.reshape(size[1], size[0], -1), (w, h), interpolation=cv2.INTER_LINEAR)
    den = cv2.resize(den, (w, h), interpolation=cv2.INTER_LINEAR)
    drawn = num.reshape(h, w, -1) / np.maximum(den, 1e-6)[..., None]
    return np.where(mask[..., None], image - drawn, 0.0)


def ceiling_db(sq_error: float, values: int) -> float:
    """The PSNR (dB, images in [0, 1]) of a summed squared error over ``values`` values, at most :data:`MAX_DB`."""
    mse = sq_error / max(values, 1)
    return MAX_DB if mse <= 10 ** (-MAX_DB / 10) else round(-10 * math.log10(mse), 2)


def exterior_ceilings(images, masks, cells: dict[str, float]) -> dict:
    """Each grid's ceiling over one exterior part: ``images`` (N, H, W, 3) uint8 or float in [0, 1],
    ``masks`` (N, H, W) bool (the part's pixels), ``cells``: name -> cell (pixels). Returns ``{"pixels": int,
    name: dB, ...}`` over every frame's eroded mask."""
    kernel = np.ones((2 * ERODE + 1, 2 * ERODE + 1), np.uint8)
    sq = dict.fromkeys(cells, 0.0)
    pixels = 0
    for image, mask in zip(images, masks):
        image = np.asarray(image)
        image = image.astype(np.float32) / (255.0 if image.dtype == np.uint8 else 1.0)
        inner = cv2.erode(np.asarray(mask, np.uint8), kernel) > 0 if ERODE else np.asarray(mask, bool)
        pixels += int(inner.sum())
        for name, cell in cells.items():
            sq[name] += float((grid_residual(image, inner, cell) ** 2).sum())
    return {"pixels": pixels, **{name: ceiling_db(sq[name], pixels * 3) for name in cells}}


def colour_cell(ceilings: dict[str, dict], preset_cell: float, footprint: float) -> float:
    """The exterior's colour cell (m; 0: the preset's) from each part's ceilings (``{part: {"preset": dB}}``):
    :data:`CELL_PIXELS` × ``footprint`` (m a training pixel at the body) where a grid of the preset's cells
    (``preset_cell`` m) draws some part no better than :data:`PATTERN_DB` and the finer cell is finer."""
    fine = CELL_PIXELS * footprint
    if footprint <= 0 or fine >= preset_cell or not ceilings:
        return 0.0
    return round(fine, 5) if min(c["preset"] for c in ceilings.values()) < PATTERN_DB else 0.0


def colour_why(ceilings: dict[str, dict], preset_cell: float, footprint: float, cell: float) -> str:
    """Why the exterior got colour cell ``cell`` (m; 0: the preset's), in words, from the same evidence as
    :func:`colour_cell`."""
    if not ceilings:
        return "no clothing or hair to draw"
    worst = min(ceilings, key=lambda p: ceilings[p]["preset"])
    fine = CELL_PIXELS * footprint
    verdict = (f"under {PATTERN_DB:g} dB, colour cells of {1000 * cell:.1f} mm" if cell > 0 else
               "the preset's cells" + ("" if fine < preset_cell else f" ({CELL_PIXELS:g} pixels are no finer)"))  # fmt: skip
    return (f"the preset's {1000 * preset_cell:.1f}-mm colour cells draw the {worst}'s pattern to "
            f"{ceilings[worst]['preset']:g} dB in the frames ({CELL_PIXELS:g}-pixel cells of {1000 * fine:.1f} mm: "
            f"{ceilings[worst]['fine']:g} dB): {verdict}")  # fmt: skip
