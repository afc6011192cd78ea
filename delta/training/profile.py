"""Throughput of a training step against the machine's limit.

* ``matmul_peak``: the machine's measured float32 matrix-multiply rate (FLOP/s) with the
  threads a job gets — the practical ceiling of dense network work on this node.
* ``profile_steps``: FLOPs of one training step (forward and backward) counted by
  ``torch.utils.flop_counter.FlopCounterMode`` — matrix multiplies and convolutions only,
  the work a roofline is about; element-wise work (encodings, kNN, compositing) is not
  counted, so the achieved fraction is a lower bound of how busy the step keeps the cores —
  and the wall time, samples and FLOP/s of a few timed steps.
"""

from __future__ import annotations

import dataclasses
import time

import torch
from torch.utils.flop_counter import FlopCounterMode

from delta import losses as L
from delta.data.frames import FrameData, sample_rays
from delta.models.avatar import HybridAvatar
from delta.training.presets import TrainSettings
from delta.training.trainer import _to, loss_terms


def matmul_peak(n: int = 1024, repeats: int = 20, dtype=torch.float32, device: str = "cpu") -> float:
    """Best FLOP/s of an n×n by n×n product over ``repeats`` runs (2 n³ FLOPs each)."""
    a = torch.randn(n, n, dtype=dtype, device=device)
    b = torch.randn(n, n, dtype=dtype, device=device)
    best = float("inf")
    for _ in range(3):  # warm up the kernels and the caches
        a @ b
    for _ in range(repeats):
        if device != "cpu":
            torch.cuda.synchronize()
        t = time.perf_counter()
        a @ b
        if device != "cpu":
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t)
    return 2 * n**3 / best


@dataclasses.dataclass
class StepProfile:
    flops: float
    """Counted FLOPs of one step (forward + backward, matmul/conv only)."""
    seconds: float
    """Median wall time of a step."""
    samples: float
    """Mean NeRF samples evaluated a step (after culling)."""
    rays: int

    @property
    def flops_per_s(self) -> float:
        return self.flops / self.seconds

    @property
    def samples_per_s(self) -> float:
        return self.samples / self.seconds


def _step(model: HybridAvatar, data: FrameData, st: TrainSettings, stage: int, g: torch.Generator) -> int:
    cfg = st.stage1 if stage == 1 else st.stage2
    frame = int(data.train[torch.randint(len(data.train), (1,), generator=g)])
    dev = model.background.device
    batch = _to(sample_rays(data, frame, cfg.rays, g), dev)
    terms, r = loss_terms(model, batch, st, data.skin_color.to(dev), None, g)
    loss = L.total(terms, st.weights)
    model.zero_grad(set_to_none=True)
    loss.backward()
    return r.samples_evaluated


def profile_steps(model: HybridAvatar, data: FrameData, st: TrainSettings, stage: int, steps: int = 5,
                  seed: int = 0) -> StepProfile:  # fmt: skip
    """FLOPs of one step and the median time of ``steps`` more (the model's parameters are not changed)."""
    g = torch.Generator().manual_seed(seed)
    counter = FlopCounterMode(display=False)
    with counter:
        _step(model, data, st, stage, g)
    times, samples = [], []
    for _ in range(steps):
        t = time.perf_counter()
        samples.append(_step(model, data, st, stage, g))
        if model.background.device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    cfg = st.stage1 if stage == 1 else st.stage2
    times.sort()
    return StepProfile(float(counter.get_total_flops()), times[len(times) // 2], sum(samples) / len(samples), cfg.rays)
