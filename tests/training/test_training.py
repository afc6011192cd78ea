"""Training: gradients reach every parameter group, exact resume, both stages end to end on tiny data."""

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest
import torch

from delta import DeltaError
from delta import losses as L
from delta.body.model import load_body_model
from delta.data.frames import load_frames, sample_rays
from delta.io import load_state
from delta.models.init import load_init
from delta.training.presets import resolve
from delta.training.run import build_avatar, run_stage
from delta.training.trainer import CHECKPOINT, loss_terms, nerf_only_terms, reproducible, train_stage

pytestmark = pytest.mark.slow

TINY = {
    "resolution": 32,
    "render": {"samples": 8},
    "stage1": {
        "iterations": 6,
        "rays": 128,
        "checkpoint_every": 2,
        "preview_every": 0,
        "log_every": 1,
        "lr_final": 0.1,
    },
    "stage2": {"iterations": 4, "rays": 128, "patch": 16, "checkpoint_every": 2, "preview_every": 2},
}


def _model(inputs, settings, stage=1):
    data = load_frames(inputs["record"], settings.resolution, settings.background, settings.box_margin)
    body = load_body_model(inputs["body"])
    return build_avatar(body, settings, load_init(inputs["init"], data), data, stage, torch.device("cpu")), data


@pytest.mark.parametrize("subject", ["tight", "loose"])
def test_every_parameter_group_gets_a_gradient(tiny_training, subject):
    st = resolve("fast", TINY)
    model, data = _model(tiny_training[subject], st)
    frame = int(data.train[0])
    batch = sample_rays(data, frame, 256, torch.Generator().manual_seed(0))
    terms, r = loss_terms(model, batch, st, data.skin_color)
    assert set(terms) == {"pixel", "silhouette", "interior_mask", "skin", "inside", "skin_inside", "edge",
                          "offset", "exterior"}  # fmt: skip
    assert all(torch.isfinite(v) for v in terms.values())
    assert r.hit.any() and (~r.hit).any() and r.samples_evaluated > 0
    L.total(terms, st.weights).backward()
    grads = {
        "pose": model.poses.grad[frame], "shape": model.betas.grad,
        "nerf": torch.cat([p.grad.flatten() for p in model.nerf.parameters() if p.grad is not None]),
        "offsets": torch.cat([p.grad.flatten() for p in model.offset_field.parameters() if p.grad is not None]),
        "albedo": torch.cat([p.grad.flatten() for p in model.albedo_field.parameters() if p.grad is not None]),
    }  # fmt: skip
    if model.pinhole:
        grads["translation"] = model.transl.grad[frame]
    else:
        grads["camera"] = torch.cat([model.ortho_scale.grad[frame : frame + 1], model.ortho_trans.grad[frame]])
    for name, g in grads.items():
        assert torch.isfinite(g).all() and g.abs().sum() > 0, f"no gradient reaches {name}"
    # frames not in the batch get none
    other = [f for f in range(len(data.frame_ids)) if f != frame][0]
    assert model.poses.grad[other].abs().sum() == 0


def test_per_vertex_albedo_detail_is_trained_and_held_to_zero(tiny_training):
    """With albedo.vertex_detail the rays' colour reaches the vertices they hit, and the term that holds
    the detail near zero is in the objective."""
    st = resolve("fast", TINY, {"albedo": {"vertex_detail": True}, "weights": {"vertex_detail": 2.0}})
    model, data = _model(tiny_training["tight"], st)
    batch = sample_rays(data, int(data.train[0]), 256, torch.Generator().manual_seed(0))
    terms, r = loss_terms(model, batch, st, data.skin_color)
    assert float(terms["vertex_detail"].detach()) == 0.0 and model.offset_field.detail is None
    L.total(terms, st.weights).backward()
    g = model.albedo_field.detail.grad.abs().sum(-1)
    assert torch.isfinite(g).all() and 0 < int((g > 0).sum()) < len(g) // 2  # the vertices under the rays only
    with torch.no_grad():
        model.albedo_field.detail.fill_(0.5)
    terms, _ = loss_terms(model, batch, st, data.skin_color)
    assert float(terms["vertex_detail"].detach()) == pytest.approx(3 * 0.25)


def test_empty_background_term_is_the_background_rays_optical_depth(tiny_training):
    """With weights.empty_background the objective holds β τ over the batch (β = 1 - 2 M clamped, τ the
    exterior's optical depth, 1 - e^-τ the NeRF mask); its gradient reaches the NeRF and not the albedo."""
    st = resolve("fast", TINY, {"weights": {"empty_background": 0.3}})
    model, data = _model(tiny_training["loose"], st)
    batch = sample_rays(data, int(data.train[0]), 256, torch.Generator().manual_seed(0))
    terms, r = loss_terms(model, batch, st, data.skin_color)
    assert "empty_background" not in loss_terms(model, batch, resolve("fast", TINY), data.skin_color)[0]
    torch.testing.assert_close(r.nerf_mask, 1 - torch.exp(-r.optical_depth), rtol=0, atol=1e-6)
    beta = (1 - 2 * batch.person).clamp(0, 1)
    assert float((beta * r.optical_depth).detach().sum()) > 0  # the tiny model has density on background rays
    torch.testing.assert_close(terms["empty_background"], (beta * r.optical_depth).mean())
    model.zero_grad()
    terms["empty_background"].backward()
    nerf = torch.cat([p.grad.flatten() for p in model.nerf.parameters() if p.grad is not None])
    assert torch.isfinite(nerf).all() and nerf.abs().sum() > 0
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.albedo_field.parameters())


def test_shell_term_is_the_batch_s_optical_depth_beyond_the_shell(tiny_training):
    """With render.shell the objective holds the mean of the rays' optical depth beyond it (none without a
    shell, none at weight 0); a shell beyond the room charges nothing, one at the body charges most."""
    on = {"render": {"shell": 0.01}}
    st = resolve("fast", TINY, on)
    model, data = _model(tiny_training["loose"], st)
    batch = sample_rays(data, int(data.train[0]), 256, torch.Generator().manual_seed(0))
    terms, r = loss_terms(model, batch, st, data.skin_color)
    assert (
        "shell"
        not in loss_terms(model, batch, resolve("fast", TINY, on, {"weights": {"shell": 0}}), data.skin_color)[0]
    )
    torch.testing.assert_close(terms["shell"], r.shell_depth.mean())
    assert 0 < float(terms["shell"].detach()) and (r.shell_depth <= r.optical_depth + 1e-6).all()
    model.zero_grad()
    terms["shell"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.nerf.parameters())
    spec = model.spec
    for shell, charged in ((st.avatar.render.max_dist, 0.0), (0.0, None)):  # beyond the room; off
        other = resolve("fast", TINY, {"render": {"shell": shell}})
        model.spec = dataclasses.replace(spec, render=other.avatar.render)
        got = loss_terms(model, batch, other, data.skin_color)[0].get("shell")
        assert got is None if charged is None else float(got.detach()) == charged


def test_distortion_term_is_the_batch_s_mean_spread_in_depth(tiny_training):
    """With weights.distortion the objective holds the rays' mean distortion (none at weight 0): finite,
    positive where the exterior has density, and its gradient reaches the NeRF and nothing of the mesh's
    colour."""
    st = resolve("fast", TINY, {"weights": {"distortion": 1.0}})
    model, data = _model(tiny_training["loose"], st)
    batch = sample_rays(data, int(data.train[0]), 256, torch.Generator().manual_seed(0))
    terms, r = loss_terms(model, batch, st, data.skin_color)
    assert "distortion" not in loss_terms(model, batch, resolve("fast", TINY), data.skin_color)[0]
    torch.testing.assert_close(terms["distortion"], r.distortion.mean())
    assert torch.isfinite(r.distortion).all() and float(terms["distortion"].detach()) > 0
    model.zero_grad()
    terms["distortion"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.nerf.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.albedo_field.parameters())


_RELU_NOISE = {"nerf": {"density_activation": "relu", "density_noise": 1.0, "density_noise_steps": 4}}


@pytest.mark.parametrize("over", [{}, _RELU_NOISE, {**_RELU_NOISE, "stage1": {"nerf_warmup": 5}}],
                         ids=["exp", "relu_noise", "nerf_warmup"])  # fmt: skip
def test_interrupted_stage_resumes_to_the_same_parameters(tiny_training, tmp_path, over):
    """Bit for bit on two threads (a CPU stage runs torch's deterministic kernels: without them the
    gathers' backward adds from both threads in any order); with SCARF's noisy ReLU density too (the
    noise is drawn from the step), and with a NeRF-only warm-up that the interruption (step 4) cuts in two."""
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        _resume_equivalence(tiny_training, tmp_path, over)
    finally:
        torch.set_num_threads(threads)


def test_a_converged_stage_anneals_stops_early_and_resumes_exactly(tiny_training, tmp_path):
    """plateau_gain 1000 dB: converged at the first check (step 4 with windows of 2); the learning rates
    then decay to lr_final over 10% of 40 steps: the stage stops at step 8, and a run killed at step 6
    resumes to the same parameters (the plateau is found again from the checkpoint's loss rows)."""
    over = {"stage1": {"iterations": 40, "plateau_window": 2, "plateau_gain": 1000.0, "anneal": 0.1}}
    st = resolve("fast", TINY, over)
    inputs = tiny_training["tight"]
    model_a, data = _model(inputs, st)
    res_a = train_stage(1, model_a, data, st, tmp_path / "a")
    assert res_a.steps == 8 and list(res_a.losses["step"]) == list(range(1, 9))
    groups = load_state(tmp_path / "a" / CHECKPOINT)["optimizer"]["param_groups"]
    assert groups[0]["lr"] == pytest.approx(st.stage1.lr["fields"] * 0.1)  # annealed to lr_final at step 8
    model_b, _ = _model(inputs, st)
    train_stage(1, model_b, data, st, tmp_path / "b", max_steps=6)
    model_c, _ = _model(inputs, st)
    res_c = train_stage(1, model_c, data, st, tmp_path / "b")
    assert res_c.steps == 8
    for k, v in model_a.state_dict().items():
        assert torch.equal(v, model_c.state_dict()[k]), f"{k} differs after resuming"


def _resume_equivalence(tiny_training, tmp_path, over):
    st = resolve("fast", TINY, over)
    inputs = tiny_training["loose"]
    model_a, data = _model(inputs, st)
    train_stage(1, model_a, data, st, tmp_path / "a")
    assert model_a.nerf.noise_std == 0  # a trained model renders without noise
    model_b, _ = _model(inputs, st)
    train_stage(1, model_b, data, st, tmp_path / "b", max_steps=4)  # "killed" after the checkpoint at step 4
    assert load_state(tmp_path / "b" / CHECKPOINT)["step"] == 4
    model_c, _ = _model(inputs, st)  # a fresh process: everything comes from the checkpoint
    res = train_stage(1, model_c, data, st, tmp_path / "b")
    # the learning rates decayed to lr_final at the last step (5 of 0..5), in both runs
    for run in ("a", "b"):
        groups = load_state(tmp_path / run / CHECKPOINT)["optimizer"]["param_groups"]
        assert groups[0]["lr"] == pytest.approx(st.stage1.lr["fields"] * 0.1)
    assert res.steps == 6 and list(res.losses["step"]) == list(range(1, 7))
    a, c = model_a.state_dict(), model_c.state_dict()
    assert a.keys() == c.keys()
    for k in a:
        assert torch.equal(a[k], c[k]), f"{k} differs after resuming"
    la = pd.read_csv(tmp_path / "a" / "losses.csv")
    lc = pd.read_csv(tmp_path / "b" / "losses.csv")
    # wall time accumulates across the resume; everything else is identical
    assert (lc["seconds"].diff().dropna() >= 0).all() and (la["seconds"] > 0).all()
    pd.testing.assert_frame_equal(la.drop(columns="seconds"), lc.drop(columns="seconds"))


def test_reproducible_makes_a_two_thread_gather_backward_bit_exact():
    """The op that made two 2-thread runs of a stage part: the backward of x[idx] with repeated
    indices. Under ``reproducible`` it is the same bits every time; the previous mode comes back,
    and a non-CPU device is left alone."""
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    idx = torch.randint(0, 1000, (400_000,), generator=torch.Generator().manual_seed(0))
    weight = torch.randn(400_000, 3, generator=torch.Generator().manual_seed(1))

    def grad():
        x = torch.randn(1000, 3, generator=torch.Generator().manual_seed(2)).requires_grad_()
        (x[idx] * weight).sum().backward()
        return x.grad

    try:
        assert not torch.are_deterministic_algorithms_enabled()
        with reproducible(torch.device("cpu")):
            assert torch.are_deterministic_algorithms_enabled()
            first = grad()
            assert all(torch.equal(first, grad()) for _ in range(3))
        assert not torch.are_deterministic_algorithms_enabled()
        with reproducible(torch.device("cuda")):  # only the device's type is read: no GPU needed
            assert not torch.are_deterministic_algorithms_enabled()
        # and the same numbers, to float32 rounding of ~400-term sums, as the default kernels
        torch.testing.assert_close(first, grad(), rtol=1e-5, atol=1e-4)
    finally:
        torch.set_num_threads(threads)


def test_nerf_warmup_trains_the_nerf_alone_on_the_person(tiny_training, tmp_path):
    """SCARF's stage 0: the first steps move the NeRF (and what places its samples), never the mesh's
    colour; their objective is the NeRF over the background against the image and the person mask."""
    st = resolve("fast", TINY, {"stage1": {"iterations": 3, "nerf_warmup": 3, "lr": {"nerf_warmup": 3e-3}}})
    model, data = _model(tiny_training["loose"], st)
    albedo = [p.detach().clone() for p in model.albedo_field.parameters()]
    nerf = [p.detach().clone() for p in model.nerf.parameters()]
    res = train_stage(1, model, data, st, tmp_path)
    assert all(torch.equal(a, p) for a, p in zip(albedo, model.albedo_field.parameters()))
    assert any(not torch.equal(a, p) for a, p in zip(nerf, model.nerf.parameters()))
    assert set(res.losses.columns) == {"step", "loss", "psnr", "samples", "seconds", "warmup", "pixel", "exterior"}
    assert (res.losses["warmup"] == 1).all()
    # the NeRF's own warm-up rate (SCARF's stage 0 at 5e-4, its hybrid at 1e-4), decayed like the rest
    groups = {g["name"]: g["lr"] for g in load_state(tmp_path / CHECKPOINT)["optimizer"]["param_groups"]}
    assert groups["nerf"] == pytest.approx(3e-3 * st.stage1.lr_factor(2))
    assert groups["fields"] == pytest.approx(st.stage1.lr["fields"] * st.stage1.lr_factor(2))
    # the loss is the NeRF-only render's, by hand on a fresh batch
    batch = sample_rays(data, int(data.train[0]), 64, torch.Generator().manual_seed(1), crop=0.5)
    terms, r = nerf_only_terms(model, batch, st)
    assert r.hit.any()
    torch.testing.assert_close(r.rgb, r.nerf_rgb)  # the NeRF over the background: no mesh colour in it
    torch.testing.assert_close(terms["exterior"], (r.nerf_mask - batch.person).abs().mean())
    with pytest.raises(DeltaError, match="stage2.nerf_warmup"):
        resolve("fast", {"stage2": {"nerf_warmup": 10}})
    with pytest.raises(DeltaError, match="stage1.nerf_warmup_crop"):
        resolve("fast", {"stage1": {"nerf_warmup_crop": 0.0}})


def test_learning_rate_decay_by_hand():
    cfg = resolve("fast", {"stage1": {"iterations": 5, "lr_final": 0.01}}).stage1
    assert [cfg.lr_factor(s) for s in range(5)] == pytest.approx([1.0, 0.01**0.25, 0.1, 0.01**0.75, 0.01])
    with pytest.raises(DeltaError, match="stage1.lr_final"):
        resolve("fast", {"stage1": {"lr_final": 0.0}})


def test_both_stages_end_to_end(tiny_training, tmp_path, perceptual_weights):
    inputs = tiny_training["tight"]
    s1 = run_stage(1, inputs["record"], inputs["body"], inputs["init"], str(tmp_path / "stage1"), "fast", [TINY])
    assert s1["steps"] == 6
    first = load_state(tmp_path / "stage1" / "model.pt")
    assert first["nerf"] and not first["deformation"]
    s2 = run_stage(2, inputs["record"], inputs["body"], str(tmp_path / "stage1" / "model.pt"),
                   str(tmp_path / "stage2"), "fast", [TINY], perceptual_dir=str(perceptual_weights))  # fmt: skip
    assert s2["steps"] == 4
    second = load_state(tmp_path / "stage2" / "model.pt")
    # F_e's units, counted over its box at the training times: 4 steps leave most of a fresh head active
    width = second["model"]["deformation.head.out.weight"].shape[1]
    assert len(s2["deformation_units_active"]) == 3 and min(s2["deformation_units_active"]) > width // 2
    assert second["deformation"] and any(k.startswith("deformation.") for k in second["model"])
    # stage 2 starts from stage 1: the shared parameters moved on from there, the body is the same size
    assert second["model"]["betas"].shape == first["model"]["betas"].shape
    losses = pd.read_csv(tmp_path / "stage2" / "losses.csv")
    assert "semantic" in losses and losses["semantic"].notna().all() and (losses["semantic"] > 0).all()
    assert len(list((tmp_path / "stage2" / "previews").glob("*.png"))) == 2
    settings = json.loads((tmp_path / "stage2" / "settings.json").read_text())
    assert settings["stage"] == 2 and settings["settings"]["resolution"] == 32


def test_a_refitted_body_is_trained_again_not_resumed(tiny_training, tmp_path, caplog):
    """The same settings and frames from another init fit: the finished checkpoint of the first fit is not this
    run's (it would write out an avatar of the old fit's body), so the stage trains from the start."""
    inputs = tiny_training["tight"]
    init = dict(np.load(inputs["init"]))
    start = tmp_path / "params.npz"
    np.savez(start, **init)
    out = str(tmp_path / "stage1")
    run_stage(1, inputs["record"], inputs["body"], str(start), out, "fast", [TINY])
    caplog.clear()
    with caplog.at_level("INFO"):
        run_stage(1, inputs["record"], inputs["body"], str(start), out, "fast", [TINY])
    assert "the stage is finished" in caplog.text  # the same fit: finished work, written out
    np.savez(start, **(init | {"betas": init["betas"] + 0.2}))
    caplog.clear()
    with caplog.at_level("INFO"):
        again = run_stage(1, inputs["record"], inputs["body"], str(start), out, "fast", [TINY])
    assert "not resuming" in caplog.text and "the stage is finished" not in caplog.text
    assert again["steps"] == 6
    trained = load_state(tmp_path / "stage1" / "model.pt")["model"]["betas"].double().cpu().reshape(-1)
    new, old = (torch.from_numpy(b).double().reshape(-1)[: len(trained)] for b in (init["betas"] + 0.2, init["betas"]))
    assert (trained - new).norm() < (trained - old).norm()  # the avatar of the refitted body


def test_no_exterior_means_no_nerf(tiny_training):
    st = resolve("fast", TINY, {"exterior": "no"})
    model, data = _model(tiny_training["tight"], st)
    assert model.nerf is None
    batch = sample_rays(data, int(data.train[0]), 64, torch.Generator().manual_seed(0))
    terms, r = loss_terms(model, batch, st, data.skin_color)
    assert "exterior" not in terms and r.samples_evaluated == 0 and (r.nerf_mask == 0).all()


def test_bad_settings_name_the_key():
    with pytest.raises(DeltaError, match="unknown preset 'fastest'"):
        resolve("fastest")
    with pytest.raises(DeltaError, match="sampels"):
        resolve("fast", {"render": {"sampels": 3}})


def test_a_killed_training_process_resumes_to_the_same_result(tiny_training, tmp_path):
    """`delta train` killed (SIGKILL) after its first checkpoint, rerun: same model as a run never killed."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from delta.cli import main

    inputs = tiny_training["loose"]
    over = json.dumps({**TINY, "stage1": {**TINY["stage1"], "iterations": 8, "checkpoint_every": 2}})

    def args(out):
        return ["train", "--stage", "1", "--record", inputs["record"], "--body", inputs["body"], "--start",
                inputs["init"], "--out", str(out), "--settings", over, "--threads", "1"]  # fmt: skip

    def cmd(out):
        return [sys.executable, "-m", "delta.cli", *args(out)]

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    assert main(args(tmp_path / "whole")) == 0  # the run never killed: in this process, as the command runs it
    proc = subprocess.Popen(cmd(tmp_path / "killed"), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ckpt = tmp_path / "killed" / CHECKPOINT
    deadline = time.time() + 120
    while not ckpt.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL, "the run finished before it could be killed"
    assert not (tmp_path / "killed" / "model.pt").exists()
    assert load_state(ckpt)["step"] < 8
    subprocess.run(cmd(tmp_path / "killed"), check=True, env=env, capture_output=True)
    a = load_state(tmp_path / "whole" / "model.pt")["model"]
    b = load_state(tmp_path / "killed" / "model.pt")["model"]
    for k in a:
        assert torch.equal(a[k], b[k]), f"{k} differs after the kill and resume"


def test_only_the_visited_frames_move(tiny_training, tmp_path):
    """Per-frame pose and camera change only in the steps that render their frame (no momentum drift)."""
    st = resolve("fast", TINY, {"stage1": {"iterations": 3}})
    model, data = _model(tiny_training["loose"], st)
    before = [p.detach().clone() for p in model.per_frame_parameters()]
    train_stage(1, model, data, st, tmp_path)
    moved = set()
    for p, old in zip(model.per_frame_parameters(), before):
        moved |= {int(i) for i in torch.nonzero((p.detach() != old).reshape(len(old), -1).any(1))}
    assert 1 <= len(moved) <= 3 and moved <= {int(f) for f in data.train}


def test_cuda_asked_for_without_a_gpu_is_a_clear_error(monkeypatch):
    from delta.training.run import pick_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(DeltaError, match="device: cuda is configured but torch sees no CUDA device"):
        pick_device("cuda")
    assert pick_device("auto") == torch.device("cpu")


def test_init_fit_from_another_record_is_refused(tiny_training, tmp_path):
    from delta.io import save_npz

    st = resolve("fast", TINY)
    data = load_frames(tiny_training["tight"]["record"], st.resolution)
    z = dict(np.load(tiny_training["tight"]["init"]))
    save_npz(tmp_path / "init.npz", **{**z, "frame_ids": z["frame_ids"][:-1], "poses": z["poses"][:-1]})
    with pytest.raises(DeltaError, match="differ from the frame record's"):
        load_init(tmp_path / "init.npz", data)


def test_stage_two_goes_on_at_the_rates_stage_one_ended_at(tiny_training):
    """`fast`'s stage 2 starts its fields and NeRF at stage 1's base rates times its decay (where stage 1 ended),
    its new deformation at its own rate, below the NeRF's full rate (at which its head died: test_deformation_rate.py);
    an lr table without ``deformation`` gives F_e the NeRF's."""
    st = resolve("fast", TINY)
    model, _ = _model(tiny_training["loose"], st, stage=2)
    groups = {g["name"]: g["lr"] for g in model.param_groups(st.stage2.lr)}
    one = st.stage1
    assert groups["fields"] == pytest.approx(one.lr["fields"] * one.lr_final)
    assert groups["nerf"] == pytest.approx(one.lr["nerf"] * one.lr_final)
    assert (
        groups["deformation"] == pytest.approx(st.stage2.lr["deformation"]) and groups["deformation"] < one.lr["nerf"]
    )
    plain = {k: v for k, v in st.stage2.lr.items() if k != "deformation"}
    assert {g["name"]: g["lr"] for g in model.param_groups(plain)}["deformation"] == plain["nerf"]
