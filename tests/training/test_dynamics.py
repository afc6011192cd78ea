"""F_e's time input: each frame's place in the training sequence, the time-free fallback, its settings."""

import numpy as np
import pytest
import torch

from delta import DeltaError
from delta.body.model import load_body_model
from delta.data.frames import frame_times, load_frames, sample_rays
from delta.io import load_state
from delta.models.init import load_init
from delta.training.presets import resolve
from delta.training.run import build_avatar
from delta.training.trainer import loss_terms


def test_frame_times_by_hand():
    ids = np.array([10, 11, 12, 13, 14, 15, 40, 41])
    train = np.array([0, 1, 3, 5])  # ids 10, 11, 13, 15; 12 and 14 are held-out views between them
    tau = frame_times(ids, train).numpy()
    np.testing.assert_allclose(tau[:6], [0.0, 0.2, 0.4, 0.6, 0.8, 1.0], atol=1e-7)
    assert np.isnan(tau[6:]).all()  # a novel-pose sequence after the training one: no time
    # with the splits: a held-out view just past either end is of the training sequence, a novel pose is not
    ids = np.array([9, 10, 11, 12, 13, 40])
    split = np.array([1, 0, 1, 0, 1, 2])
    tau = frame_times(ids, np.array([1, 3]), split).numpy()
    np.testing.assert_allclose(tau[:5], [0.0, 0.0, 0.5, 1.0, 1.0], atol=1e-7)
    assert np.isnan(tau[5]) and np.isnan(frame_times(ids, np.array([1, 3])).numpy()[[0, 4]]).all()


def test_one_training_frame_has_time_zero():
    tau = frame_times(np.array([5, 6]), np.array([0])).numpy()
    assert tau[0] == 0.0 and np.isnan(tau[1])


@pytest.mark.parametrize("bad", [{"time_freqs": -1}, {"dropout": 1.0}, {"phase": 2}])
def test_bad_dynamics_settings_name_the_key(bad):
    with pytest.raises(DeltaError, match="training.dynamics"):
        resolve("fast", {"dynamics": bad})


def test_the_paper_preset_keeps_the_pose_only_deformation():
    assert resolve("paper").avatar.time_freqs == 0
    st = resolve("fast")
    assert st.avatar.time_freqs == 6 and st.time_dropout == pytest.approx(0.2)
    assert resolve("fast", {"dynamics": {"time_freqs": 0}}).avatar.time_freqs == 0


@pytest.mark.slow
def test_stage2_time_input_reaches_the_render(tiny_training):
    st = resolve("fast", {"resolution": 32, "render": {"samples": 8}, "dynamics": {"time_freqs": 4}})
    inputs = tiny_training["loose"]
    data = load_frames(inputs["record"], st.resolution, st.background, st.box_margin)
    model = build_avatar(load_body_model(inputs["body"]), st, load_init(inputs["init"], data), data, 2,
                         torch.device("cpu"))  # fmt: skip
    expected = frame_times(data.frame_ids, data.train, data.split)
    torch.testing.assert_close(model.frame_time, expected, equal_nan=True)
    with torch.no_grad():  # a trained F_e (its output layer starts at zero)
        for p in model.deformation.head.parameters():
            p.normal_(0, 0.5)
    frame = int(data.train[len(data.train) // 2])
    batch = sample_rays(data, frame, 256, torch.Generator().manual_seed(0))
    timed, r = loss_terms(model, batch, st, data.skin_color, generator=torch.Generator().manual_seed(1))
    free, q = loss_terms(model, batch, st, data.skin_color, generator=torch.Generator().manual_seed(1), timeless=True)
    assert r.samples_evaluated > 0 and not torch.equal(r.rgb, q.rgb)
    timed["pixel"].backward()
    assert model.deformation.head.hidden[0].weight.grad[:, -8:].abs().sum() > 0


@pytest.mark.slow
def test_a_model_from_before_the_time_input_loads_pose_only(tiny_training, tmp_path, perceptual_weights):
    from delta.training.run import load_trained, run_stage

    inputs = tiny_training["loose"]
    tiny = {"resolution": 32, "render": {"samples": 8}, "dynamics": {"time_freqs": 0},
            "stage1": {"iterations": 2, "rays": 64, "preview_every": 0},
            "stage2": {"iterations": 2, "rays": 64, "patch": 0, "preview_every": 0}}  # fmt: skip
    run_stage(1, inputs["record"], inputs["body"], inputs["init"], str(tmp_path / "s1"), "fast", [tiny])
    run_stage(2, inputs["record"], inputs["body"], str(tmp_path / "s1" / "model.pt"), str(tmp_path / "s2"), "fast",
              [tiny], perceptual_dir=str(perceptual_weights))  # fmt: skip
    state = load_state(tmp_path / "s2" / "model.pt")
    del state["format"], state["settings"]["dynamics"]  # format 1, before the key existed (fast now reads time)
    torch.save(state, tmp_path / "old.pt")
    tr = load_trained(tmp_path / "old.pt", inputs["record"], inputs["body"])
    assert tr.model.spec.time_freqs == 0 and tr.model.time_code(0) is None and tr.model.trajectory is None
    state = load_state(tmp_path / "s2" / "model.pt")
    del state["format"]
    state["settings"]["dynamics"] = {"time_freqs": 3}  # written before the pose trajectory existed
    torch.save(state, tmp_path / "older.pt")
    with pytest.raises(DeltaError, match="older.pt"):  # time_freqs 3 is not what F_e was built with
        load_trained(tmp_path / "older.pt", inputs["record"], inputs["body"])
    state["settings"]["dynamics"] = {"time_freqs": 0}
    torch.save(state, tmp_path / "older.pt")
    assert load_trained(tmp_path / "older.pt", inputs["record"], inputs["body"]).model.trajectory is None
