"""Model only what a scene requires: occupancy during training, frozen joints, upper-body captures."""

import dataclasses

import pandas as pd
import pytest
import torch

from delta import DeltaError
from delta.body.model import load_body_model
from delta.body.parts import lower_body_joints, lower_body_vertices
from delta.data.frames import load_frames
from delta.io import load_state
from delta.models.init import load_init
from delta.scene.framing import detect_capture
from delta.training.presets import resolve
from delta.training.run import build_avatar, resolve_scope
from delta.training.scope import frozen_joints
from delta.training.trainer import CHECKPOINT, train_stage

pytestmark = pytest.mark.slow

TINY = {
    "resolution": 32,
    "render": {"samples": 8, "occupancy": {"warmup": 2, "update_every": 2, "resolution": 16, "threshold": 0.5}},
    "stage1": {"iterations": 6, "rays": 128, "checkpoint_every": 2, "preview_every": 0, "log_every": 100},
}


def _setup(inputs, *overrides):
    st = resolve("fast", TINY, *overrides)
    data = load_frames(inputs["record"], st.resolution, st.background, st.box_margin)
    body = load_body_model(inputs["body"])
    init = load_init(inputs["init"], data)
    return st, data, body, init


def _model(inputs, *overrides):
    st, data, body, init = _setup(inputs, *overrides)
    return build_avatar(body, st, init, data, 1, torch.device("cpu")), data, st


def test_occupancy_skips_samples_after_warmup_and_resumes_exactly(tiny_training, tmp_path):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # bitwise equality needs one thread
    try:
        inputs = tiny_training["loose"]
        model_a, data, st = _model(inputs)
        assert model_a.occupancy is not None and "occupancy.occupied" in model_a.state_dict()
        train_stage(1, model_a, data, st, tmp_path / "a")
        assert bool(model_a.occupancy.active)
        # the same run without the grid draws the same rays (the grid uses no shared randomness)
        model_n, _, st_n = _model(inputs, {"render": {"occupancy": {"enabled": False}}})
        train_stage(1, model_n, data, st_n, tmp_path / "n")
        la, ln = (pd.read_csv(tmp_path / x / "losses.csv") for x in ("a", "n"))
        assert list(la["samples"][:2]) == list(ln["samples"][:2])  # warm-up: nothing skipped
        assert (la["samples"][2:] < ln["samples"][2:]).all() and la["samples"][2] > 0
        # interrupted after the grid's first updates, resumed in a fresh model: bit for bit the same
        model_b, _, _ = _model(inputs)
        train_stage(1, model_b, data, st, tmp_path / "b", max_steps=4)
        assert load_state(tmp_path / "b" / CHECKPOINT)["step"] == 4
        model_c, _, _ = _model(inputs)
        train_stage(1, model_c, data, st, tmp_path / "b")
        a, c = model_a.state_dict(), model_c.state_dict()
        for k in a:
            assert torch.equal(a[k], c[k]), f"{k} differs after resuming"
    finally:
        torch.set_num_threads(threads)


def test_an_early_grid_skips_samples_before_the_warmup_and_keeps_the_body_shell(tiny_training, tmp_path):
    inputs = tiny_training["loose"]
    early = {"render": {"max_dist": 0.15, "occupancy": {"warmup": 4, "early": 2, "early_shell": 0.0, "resolution": 48}}}
    model_e, data, st = _model(inputs, early)
    train_stage(1, model_e, data, st, tmp_path / "e", max_steps=3)  # one early update (step 2)
    occ = model_e.occupancy
    assert occ.shell.any() and bool(occ.active) and (occ.occupied | ~occ.shell).all()
    assert (occ.shell & ~occ._core()).any()  # cells the young density alone would have emptied
    train_stage(1, model_e, data, st, tmp_path / "e")
    model_n, _, st_n = _model(inputs, {"render": {"max_dist": 0.15, "occupancy": {"enabled": False}}})
    train_stage(1, model_n, data, st_n, tmp_path / "n")
    le, ln = (pd.read_csv(tmp_path / x / "losses.csv") for x in ("e", "n"))
    assert list(le["samples"][:2]) == list(ln["samples"][:2])  # before the early update: nothing skipped
    assert (le["samples"][2:] < ln["samples"][2:]).all()  # from it on, before the warm-up's end too


def test_the_grid_updates_from_early_on_except_a_carried_stage_2():
    import types

    from delta.training.trainer import _maybe_update_occupancy

    grid = types.SimpleNamespace(shape=(1, 1, 1), fraction=lambda: 1.0, shell_reach=0.1)

    def updates(stage=1, carry=True, early=2, room=0.3):
        """{step: early} of the updates in steps 0-7 (warm-up 4, every 2 steps; the preset's 5-cm shell)."""
        occupancy = {"warmup": 4, "early": early, "update_every": 2, "carry": carry}
        st = resolve("fast", {"render": {"max_dist": room, "occupancy": occupancy}})
        made = {}
        for step in range(8):
            model = types.SimpleNamespace(
                occupancy=grid, update_occupancy=lambda seed, early: made.update({step: early})
            )
            _maybe_update_occupancy(model, st, stage, step)
        return made

    assert updates() == updates(stage=2, carry=False) == {2: True, 4: False, 6: False}
    assert updates(stage=2) == {4: False, 6: False}  # stage 1's grid is not young
    assert updates(early=4) == updates(early=9) == updates(early=0) == {4: False, 6: False}  # no early phase
    # a room at most twice the shell's reach: its cells past the shell are the exterior's outer ones, none early
    assert updates(room=0.2) == {4: False, 6: False} and updates(room=0.21) == updates()


def test_stage2_starts_from_stage1s_grid_grown_by_fe_reach(tiny_training, tmp_path):
    inputs = tiny_training["loose"]
    # cells fine enough that stage 1's set, grown by F_e's reach, leaves part of the tiny box empty (1 %)
    fine = {"render": {"occupancy": {"resolution": 32}}}
    model1, data, st = _model(inputs, fine)
    train_stage(1, model1, data, st, tmp_path / "s1")
    assert bool(model1.occupancy.active) and model1.occupancy.fraction() < 1
    stage2 = {"stage2": {"iterations": 2, "rays": 128, "checkpoint_every": 2, "preview_every": 0, "log_every": 100}}
    runs = {}
    for carry in (True, False):
        st2, data, body, init = _setup(inputs, stage2, fine, {"render": {"occupancy": {"carry": carry}}})
        model2 = build_avatar(body, st2, init, data, 2, torch.device("cpu"))
        missing, _ = model2.load_state_dict(model1.state_dict(), strict=False)
        assert all(k.startswith("deformation.") for k in missing)
        assert model2.occupancy.dilation >= 1  # F_e's reach in cells
        train_stage(2, model2, data, st2, tmp_path / f"s2_{carry}")
        runs[carry] = (model2.occupancy, pd.read_csv(tmp_path / f"s2_{carry}" / "losses.csv"))
    carried, reset = runs[True][0], runs[False][0]
    assert not bool(reset.active) and reset.occupied.all()  # 2 steps < warm-up: every cell, the grid unused
    assert bool(carried.active) and torch.equal(carried.density, model1.occupancy.density)
    # stage 1's occupied set (threshold from the same densities) grown by F_e's reach, whole cells
    grown = torch.nn.functional.max_pool3d(model1.occupancy.occupied[None, None].float(), 2 * carried.dilation + 1,
                                           stride=1, padding=carried.dilation)[0, 0] > 0  # fmt: skip
    assert torch.equal(carried.occupied, grown) and model1.occupancy.fraction() < carried.fraction() < 1
    # the same rays: from the first step never more samples, fewer in all
    samples = {carry: run[1]["samples"] for carry, run in runs.items()}
    assert (samples[True] <= samples[False]).all() and samples[True].sum() < samples[False].sum()


def test_frozen_joints_stay_exactly_at_the_init(tiny_training, tmp_path):
    inputs = tiny_training["tight"]
    model, data, st = _model(inputs, {"freeze": ["lowerarm01.L", "lowerarm01.R", "spine03"], "freeze_rest": -1.0,
                                      "render": {"occupancy": {"enabled": False}}})  # fmt: skip
    names = model.body.joint_names
    frozen = list(model.spec.frozen_joints)
    assert [names[j] for j in frozen] == ["spine03", "lowerarm01.L", "lowerarm01.R"]
    init = model.poses.detach().clone()
    train_stage(1, model, data, st, tmp_path / "run")
    moved = (model.poses.detach() - init).abs().amax(-1)  # (N, J)
    assert torch.equal(model.poses.detach()[:, frozen], init[:, frozen])
    free = [j for j in range(1, model.body.num_joints) if j not in frozen]
    assert (moved[:, free] > 0).any()
    # without freezing, the same joints do move
    free_model, _, st2 = _model(inputs, {"freeze_rest": -1.0, "render": {"occupancy": {"enabled": False}}})
    train_stage(1, free_model, data, st2, tmp_path / "free")
    assert (free_model.poses.detach()[:, frozen] != init[:, frozen]).any()


def test_static_joints_and_groups_resolve_to_joint_indices(tiny_training):
    st, data, body, init = _setup(tiny_training["tight"])
    poses = torch.zeros(5, body.num_joints, 3)
    poses[:, 3, 0] = torch.linspace(0, 0.2, 5)  # a moving leg joint
    poses[:, 5, 2] = 0.3  # a constant but posed one: not at rest, stays free
    poses[:, 7, 1] = 1e-7  # within 1e-6 of rest
    rest = frozen_joints(body, [], 1e-6, poses)
    assert 7 in rest and 0 not in rest and 3 not in rest and 5 not in rest  # never the root
    assert len(rest) == body.num_joints - 3
    eyes = frozen_joints(body, ["eyes", "head"], -1.0, poses)
    assert [body.joint_names[j] for j in eyes] == ["head", "eye.L", "eye.R"]
    with pytest.raises(DeltaError, match="training.freeze: 'tail'"):
        frozen_joints(body, ["tail"], -1.0, poses)
    # the fast preset freezes what the init leaves at rest
    scope = resolve_scope(body, st, init, data)
    at_rest = init.poses[data.train].abs().amax(dim=(0, 2)) <= 1e-6
    at_rest[0] = False
    assert scope["capture"] == "full" and scope["frozen_joints"] == torch.nonzero(at_rest).squeeze(1).tolist()
    assert 0 < len(scope["frozen_joints"]) < body.num_joints - 1


def test_upper_capture_models_no_legs(tiny_training):
    st, data, body, init = _setup(tiny_training["tight"], {"render": {"occupancy": {"enabled": False}}})
    names = [body.joint_names[j] for j in lower_body_joints(body)]
    assert "upperleg01.L" in names and "foot.R" in names and "spine01" not in names and "pelvis.L" not in names
    lower = lower_body_vertices(body)
    assert 0.2 < float(lower.float().mean()) < 0.6
    full = build_avatar(body, st, init, data, 1, "cpu", {"capture": "full", "frozen_joints": []})
    upper = build_avatar(body, st, init, data, 1, "cpu", {"capture": "upper", "frozen_joints": []})
    assert not lower[upper.knn_ids].any() and lower[full.knn_ids].any()
    assert set(upper.knn_ids.tolist()) < set(full.knn_ids.tolist())
    lo_f, lo_u = full.nerf.encoding.lo, upper.nerf.encoding.lo
    cano = upper.canonical_vertices
    assert float(lo_u[1]) > float(lo_f[1]) + 0.5  # the NeRF's box stops above the knees
    assert float(lo_u[1]) == pytest.approx(float(cano[~lower, 1].min()) - st.avatar.nerf_margin, abs=1e-5)
    # a frame rendered through the upper model skins no sample from a leg vertex: the legs get no NeRF
    mesh = upper.posed_mesh(int(data.train[0]))[0]
    assert len(mesh.skinning.posed) == len(upper.knn_ids)


def test_a_capture_that_never_shows_the_legs_is_detected(tiny_training):
    st, data, body, init = _setup(tiny_training["tight"])
    args = (body, init.betas, init.poses)
    assert detect_capture(*args, init.transl, init.camera, data.train, data.resolution) == "full"
    # the same person 1.1 m lower in front of the same camera: head and shoulders fill the frame
    low = init.transl.clone()
    low[:, 1] -= 1.1
    assert detect_capture(*args, low, init.camera, data.train, data.resolution) == "upper"
    st_up = dataclasses.replace(st, capture="auto")
    init_up = dataclasses.replace(init, transl=low)
    assert resolve_scope(body, st_up, init_up, data)["capture"] == "upper"
