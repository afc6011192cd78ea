"""F_e's stage-2 rate in each preset leaves its ReLU head alive while it learns (docs/method.md, "F_e's rate").

At 1e-2 Adam's first hundred steps on a garment-like target push all but a few of the head's last-layer units
below zero on every input, for good; the head is then nearly its output bias, whatever it was meant to learn.
"""

import math

import pytest
import torch

from delta.fields.networks import DeformationField, time_features
from delta.training.presets import resolve

BOX = torch.tensor([[-0.5, -1.0, -0.3], [0.5, 1.0, 0.3]])


def fit_a_sway(preset: str, rate: float | None = None, steps: int = 100) -> tuple[DeformationField, float]:
    """F_e (``preset``'s architecture) fitted by Adam at ``rate`` (default: the preset's stage-2 rate for it) to a
    hem's sway: points below the knees move 2 cm sideways and back over the sequence, the rest stay. Returns the
    field and its last step's loss (mm²)."""
    st = resolve(preset)
    if rate is None:
        rate = st.stage2.lr.get("deformation", st.stage2.lr["nerf"])
    torch.manual_seed(0)
    field = DeformationField(st.deformation, BOX, time_freqs=st.avatar.time_freqs)
    opt = torch.optim.Adam(field.parameters(), lr=rate)
    g = torch.Generator().manual_seed(1)
    for step in range(steps):
        x = field.box_points(2048, seed=step)
        tau = torch.rand((), generator=g)
        target = torch.zeros_like(x)
        target[:, 0] = 0.02 * torch.sin(2 * math.pi * tau) * (x[:, 1] < -0.3)
        posed = x + 0.01 * torch.randn(x.shape, generator=g)
        loss = ((field(x, posed, time_features(tau, field.time_freqs)) - target) ** 2).mean() * 1e6
        opt.zero_grad()
        loss.backward()
        opt.step()
    return field, float(loss.detach())


def last_layer_units(field: DeformationField) -> int:
    return field.active_units(time_features(torch.linspace(0, 1, 8), field.time_freqs), points=2048)[-1]


@pytest.mark.parametrize("preset", ["fast", "balanced"])
def test_the_presets_deformation_rate_keeps_most_of_f_es_head(preset):
    field, loss = fit_a_sway(preset)
    width = field.head.hidden[-1].out_features
    assert last_layer_units(field) >= width // 2
    assert loss < 10.0  # and learns the sway: 47 mm² at the first step


def test_at_1e_2_the_head_dies():
    """The guard above can fail: the same fit at 1e-2 leaves under a quarter of the last layer."""
    field, _ = fit_a_sway("fast", 1e-2)
    assert last_layer_units(field) < field.head.hidden[-1].out_features // 4
