"""Coarse to fine: after a stage's switch step its rays come from larger frames, in the model's pixel
units; an interruption at the switch resumes bit-exactly; the workflow's loader finds the fine frames."""

from __future__ import annotations

import pytest
import torch

from delta import DeltaError
from delta.data.frames import load_frames
from delta.training.presets import deep_merge, resolve
from delta.training.run import fine_frames
from delta.training.trainer import rays_at, train_stage
from tests.training.test_training import TINY, _model

C2F = deep_merge(TINY, {"stage1": {"fine_from": 0.5, "fine_resolution": 64}})


def test_fine_rays_are_the_fine_frames_pixels_in_the_models_units(tiny_training):
    st = resolve("fast", C2F)
    data = load_frames(tiny_training["tight"]["record"], 32, st.background, st.box_margin)
    fine = load_frames(tiny_training["tight"]["record"], 64, st.background, st.box_margin)
    frame = int(data.train[0])
    batch = rays_at(data, fine, frame, 500, torch.Generator().manual_seed(0))
    at_fine = (batch.pixels * 2).floor().long()  # back in the fine frames' pixels
    torch.testing.assert_close(batch.rgb, fine.images[frame, at_fine[:, 1], at_fine[:, 0]], rtol=0, atol=0)
    i0, i1, j0, j1 = (int(x) for x in fine.boxes[frame])
    assert bool((batch.pixels[:, 0] >= j0 / 2).all() and (batch.pixels[:, 0] <= j1 / 2).all())
    assert bool((batch.pixels[:, 1] >= i0 / 2).all() and (batch.pixels[:, 1] <= i1 / 2).all())
    # the same draws as a coarse batch: the generator ends in the same state
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    rays_at(data, fine, frame, 100, g1), rays_at(data, None, frame, 100, g2)
    assert torch.equal(g1.get_state(), g2.get_state())


def test_an_interruption_at_the_switch_resumes_bit_exactly(tiny_training, tmp_path):
    st = resolve("fast", C2F)
    assert st.stage1.fine_step() == 3
    inputs = tiny_training["tight"]
    fine = fine_frames(inputs["record"], st, 1)
    assert fine.resolution == 64
    whole, data = _model(inputs, st)
    ran = train_stage(1, whole, data, st, tmp_path / "whole", fine=fine)
    coarse = train_stage(1, _model(inputs, resolve("fast", TINY))[0], data, resolve("fast", TINY), tmp_path / "c")
    # the switch changes the targets from step 4 on, not before
    assert ran.losses["loss"].iloc[:3].tolist() == coarse.losses["loss"].iloc[:3].tolist()
    assert ran.losses["loss"].iloc[3:].tolist() != coarse.losses["loss"].iloc[3:].tolist()
    first, _ = _model(inputs, st)
    train_stage(1, first, data, st, tmp_path / "cut", max_steps=3, fine=fine)  # stopped at the switch
    resumed, _ = _model(inputs, st)
    again = train_stage(1, resumed, data, st, tmp_path / "cut", fine=fine)
    assert again.losses.drop(columns="seconds").equals(ran.losses.drop(columns="seconds"))
    for k, v in whole.state_dict().items():
        assert torch.equal(v, resumed.state_dict()[k]), k


def test_a_switch_without_fine_frames_is_refused_and_none_is_loaded_without_one(tiny_training, tmp_path):
    st = resolve("fast", C2F)
    model, data = _model(tiny_training["tight"], st)
    with pytest.raises(DeltaError, match="fine_from 0.5"):
        train_stage(1, model, data, st, tmp_path / "x")
    assert fine_frames(tiny_training["tight"]["record"], resolve("fast", TINY), 1) is None
    own = fine_frames(
        tiny_training["tight"]["record"], resolve("fast", deep_merge(TINY, {"stage1": {"fine_from": 0.5}})), 1
    )
    from delta.data.record import FrameRecord

    with FrameRecord(tiny_training["tight"]["record"]) as rec:
        assert own.resolution == rec.size
