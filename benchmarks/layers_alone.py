"""Each exterior layer of an avatar trained in layers, rendered alone, against where the capture allows it.

An avatar trained with ``training.layers: split`` composites its clothing and hair NeRFs; the composite
shows only the front of the two, so a layer can hold density behind the other's surface (hair inside a
skirt) that no training image sees, and that comes out when the layer is worn alone (``delta dress
--layers hair``). This renders each layer alone on training frames (the avatar's own frames, cameras
and crop), and counts, per layer, the pixels where the layer alone is
opaque (> 0.5) though neither its own mask nor the mask of a layer that may cover it (hair may cover
clothing) is set, against the layer's own mask's pixels. ``--confine``: each layer first confined to where
the avatar's own training frames see it, as ``delta dress --layers`` does (``delta.models.layer_support.confined_layers``:
8 training frames, evenly spread; mostly other frames than the scored ones).

    PYTHONPATH=$PWD python3 benchmarks/layers_alone.py --model results/synthetic/loose/stage2/model.pt \\
        --record results/synthetic/loose/frames.h5 --body resources/body/anny_sub1.npz --subject loose \\
        --label "as trained, confined" --confine --csv benchmarks/layers_alone.csv --append
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from delta.applications.dress import confine
from delta.fields.networks import LayeredNeRF
from delta.losses import layer_targets
from delta.models.image import render_image
from delta.models.layer_support import may_cover
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import device_name, model_arguments, save_table  # noqa: E402


def main(argv=None) -> None:
    ap = model_arguments(argparse.ArgumentParser(description=__doc__.split("\n\n")[0]))
    ap.add_argument("--label", required=True, help="what the avatar was trained with (a column of the CSV)")
    ap.add_argument("--frames", type=int, default=6, help="training frames scored, evenly spread")
    ap.add_argument("--confine", action="store_true", help="confine each layer as delta dress --layers does")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--csv", required=True)
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args(argv)
    trained = load_trained(a.model, a.record, a.body, a.device)
    model, data = trained.model, trained.data
    if not isinstance(model.nerf, LayeredNeRF):
        raise SystemExit(f"{a.model}: its exterior is one NeRF, not layers (train it with training.layers: split)")
    if a.confine:
        confine(trained, model.nerf.names)
    whole = model.nerf
    train = np.asarray(data.train)
    picks = train[np.linspace(0, len(train) - 1, min(a.frames, len(train))).round().astype(int)]
    rows, t0 = [], time.perf_counter()
    for i in picks:
        masks = layer_targets(data.exterior[i].float(), data.hair[i].float())
        for name in whole.names:
            model.nerf = LayeredNeRF.of({name: whole.layers[name]})
            alone = render_image(model, int(i))["nerf_mask"]
            allowed = (masks[name] + sum(masks[c] for c in may_cover(name, whole.names))).clamp(0.0, 1.0)
            rows.append({"subject": a.subject, "label": a.label, "frame": int(data.frame_ids[i]), "layer": name,
                         "mask_px": int((masks[name] > 0.5).sum()),
                         "alone_px": int((alone > 0.5).sum()),
                         "alone_outside_px": int(((alone > 0.5) & (allowed < 0.5)).sum()),
                         "alone_inside_px": int(((alone > 0.5) & (masks[name] > 0.5)).sum())})  # fmt: skip
        model.nerf = whole
    table = pd.DataFrame(rows)
    table["outside_per_mask"] = table.alone_outside_px / table.mask_px.clip(lower=1)
    table["resolution"] = model.resolution
    table["device"] = device_name(a.device, torch.get_num_threads())
    table["seconds"] = round(time.perf_counter() - t0, 1)
    save_table(table, a.csv, a.append)
    print(table.groupby(["subject", "label", "layer"])[["mask_px", "alone_outside_px", "outside_per_mask"]].mean())


if __name__ == "__main__":
    main()
