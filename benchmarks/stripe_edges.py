"""Where a striped garment's edges lie in a render against the truth, and how sharp they are: from the
evaluation's side-by-sides (``eval/worst/*.png``: truth | render | error, each the capture's size).

Down each sampled column of a region (a band of horizontal stripes), the stripe signal (a channel
difference: blue minus red for blue and white stripes) crosses its threshold at every stripe edge, in the
truth and in the render. Each truth edge is matched to the nearest render edge within ``--reach`` pixels;
its offset (render minus truth, pixels down the image) says whether the render draws the edge in its place,
and the edge's 10-90 % rise (pixels) says how sharp it is. A render whose edges are as sharp as the truth's
but scattered by a pixel or two is misregistered (the frames disagree where the stripe lies); one whose
edges are in place but wide is blurred (cells coarser than the stripe's edge). The truth's own cloth
texture moves its crossings too: ``--floor SIGMA`` adds, for each image, a row of the truth against itself
blurred by a Gaussian of SIGMA pixels (as sharp as a render), the offset a render in place would still show.

    python benchmarks/stripe_edges.py --subject talker-short --image base=eval/worst/test_view_frame_00004.png \\
        cells=/tmp/cells/worst/test_view_frame_00004.png --rows 340:512 --cols 120:400 --floor 0.8 \\
        --out benchmarks/stripe_edges.csv
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402


def crossings(profile: np.ndarray, threshold: float) -> np.ndarray:
    """Sub-pixel positions where ``profile`` (N,) crosses ``threshold`` (linear between samples)."""
    s = profile - threshold
    i = np.where(np.sign(s[:-1]) * np.sign(s[1:]) < 0)[0]
    return i + s[i] / (s[i] - s[i + 1])


def rise(profile: np.ndarray, edge: float, lo: float, hi: float, half: int = 6) -> float | None:
    """The 10-90 % rise (samples) of ``profile`` about ``edge`` between its levels ``lo`` and ``hi``: the
    samples within ``half`` of the edge whose level lies strictly between 10 % and 90 %."""
    a, b = int(round(edge)) - half, int(round(edge)) + half + 1
    if a < 0 or b > len(profile) or hi <= lo:
        return None
    level = (profile[a:b] - lo) / (hi - lo)
    return float(((level > 0.1) & (level < 0.9)).sum())


def stripe_edges(truth: np.ndarray, render: np.ndarray, signal, threshold: float, step: int = 4,
                 reach: float = 8.0) -> dict:  # fmt: skip
    """Edges of a region's horizontal stripes, truth against render ((H, W, 3) images of the region):
    edges matched, mean and mean absolute offset (pixels down), and both images' mean 10-90 % rise."""
    offsets, widths = [], {"truth": [], "render": []}
    for col in range(0, truth.shape[1], step):
        g, r = signal(truth[:, col]), signal(render[:, col])
        ge, re_ = crossings(g, threshold), crossings(r, threshold)
        if len(re_):
            d = re_[np.abs(re_[None] - ge[:, None]).argmin(1)] - ge if len(ge) else np.zeros(0)
            offsets.extend(d[np.abs(d) < reach].tolist())
        for name, p, edges in (("truth", g, ge), ("render", r, re_)):
            lo, hi = np.percentile(p, 5), np.percentile(p, 95)
            widths[name].extend(w for w in (rise(p, e, lo, hi) for e in edges) if w is not None)
    off = np.asarray(offsets)
    return {"edges": len(off), "offset_px": round(float(off.mean()), 3) if len(off) else np.nan,
            "abs_offset_px": round(float(np.abs(off).mean()), 3) if len(off) else np.nan,
            "rise_truth_px": round(float(np.mean(widths["truth"])), 3) if widths["truth"] else np.nan,
            "rise_render_px": round(float(np.mean(widths["render"])), 3) if widths["render"] else np.nan}  # fmt: skip


def blue_minus_red(pixels: np.ndarray) -> np.ndarray:
    """The stripe signal of blue and white stripes, of (N, 3) RGB pixels in [0, 1]."""
    return pixels[:, 2] - pixels[:, 0]


def side_by_side(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The truth and the render (RGB in [0, 1]) of an evaluation side-by-side (truth | render | error)."""
    im = cv2.imread(str(path))
    if im is None:
        sys.exit(f"{path}: not an image")
    im = im[..., ::-1].astype(np.float64) / 255
    w = im.shape[1] // 3
    return im[:, :w], im[:, w : 2 * w]


def span(text: str) -> slice:
    a, b = text.split(":")
    return slice(int(a), int(b))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--subject", required=True)
    ap.add_argument("--image", nargs="+", required=True, help="VARIANT=side-by-side PNG")
    ap.add_argument("--rows", type=span, required=True, help="the striped region's rows, a:b")
    ap.add_argument("--cols", type=span, required=True, help="its columns, a:b")
    ap.add_argument("--threshold", type=float, default=0.3, help="the stripe signal's edge level")
    ap.add_argument("--step", type=int, default=4, help="columns between sampled columns")
    ap.add_argument("--floor", type=float, default=0.0, help="also the truth against itself blurred by this σ (px)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args()
    rows = []
    for item in a.image:
        variant, path = item.split("=", 1)
        truth, render = side_by_side(Path(path))
        region = (a.rows, a.cols)
        row = stripe_edges(truth[region], render[region], blue_minus_red, a.threshold, a.step)
        rows.append({"subject": a.subject, "variant": variant, "image": Path(path).name, **row})
        if a.floor > 0:
            blurred = cv2.GaussianBlur(truth, (0, 0), a.floor)
            row = stripe_edges(truth[region], blurred[region], blue_minus_red, a.threshold, a.step)
            rows.append({"subject": a.subject, "variant": f"the truth blurred by {a.floor:g} px",
                         "image": Path(path).name, **row})  # fmt: skip
    print(save_table(pd.DataFrame(rows).drop_duplicates(), a.out, a.append).to_string(index=False))


if __name__ == "__main__":
    main()
