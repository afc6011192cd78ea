"""How the blur test (:mod:`delta.data.quality`) sees a clip: every frame's sharpness as a share of the
clip's median, and what a horizontal motion smear of k pixels does to one frame.

Rows ``kind=frame``: one a frame (``ratio`` to the median; below ``BLUR_RATIO`` a frame is judged
blurred); rows ``kind=smear``: the chosen frame smeared by k pixels, its ratio to its own sharp self.

    python benchmarks/blur_sharpness.py --video ../shared/real/dress_dance.mp4 \\
        --masks results/real/dress_dance/matting.h5:person --smear-frame 50 --out benchmarks/blur_sharpness.csv
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import h5py
import numpy as np
import pandas as pd

from delta.data.quality import BLUR_RATIO, sharpness
from delta.data.video import iter_video, probe_video


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--video", required=True)
    p.add_argument("--masks", required=True, help="FILE:KEY of (N, H, W) person masks 0-255 (a matting step's)")
    p.add_argument("--smear-frame", type=int, default=0)
    p.add_argument("--smear", type=int, nargs="+", default=[5, 9, 15, 25])
    p.add_argument("--out", required=True)
    args = p.parse_args()
    path, key = args.masks.rsplit(":", 1)
    info = probe_video(args.video)
    rows, scores = [], {}
    with h5py.File(path, "r") as f:
        masks = f[key]
        for i, rgb in iter_video(args.video, set(range(min(info.frames, len(masks))))):
            scores[i] = sharpness(rgb, masks[i])
            if i == args.smear_frame:
                for k in args.smear:
                    kernel = np.zeros((k, k), np.float32)
                    kernel[k // 2] = 1.0 / k
                    ratio = sharpness(cv2.filter2D(rgb, -1, kernel), masks[i]) / scores[i]
                    rows.append({"clip": Path(args.video).name, "kind": "smear", "frame": i, "smear_px": k,
                                 "ratio": round(ratio, 4)})  # fmt: skip
    median = float(np.nanmedian(list(scores.values())))
    rows += [{"clip": Path(args.video).name, "kind": "frame", "frame": i, "smear_px": 0, "ratio": round(s / median, 4)}
             for i, s in scores.items()]  # fmt: skip
    table = pd.DataFrame(rows)
    table.to_csv(args.out, index=False)
    frames = table[table.kind == "frame"].ratio
    print(f"{len(frames)} frames: ratio to the median {frames.min():.2f}-{frames.max():.2f}, "
          f"{int((frames < BLUR_RATIO).sum())} below {BLUR_RATIO}")  # fmt: skip
    print(table[table.kind == "smear"].to_string(index=False))


if __name__ == "__main__":
    main()
