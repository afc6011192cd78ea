"""Device handling: the avatar moves with its body model; CPU-generated samples drive any device.

A GPU's code paths (the tensor searches, ``grid_sample``, flat leaf tests: ``delta.devices``) run here on
the CPU and must give the CPU's step. The CUDA comparison runs where a GPU is present
(benchmarks/cuda_check.py does the same on a real subject; its CSV is in benchmarks/cuda_check.csv);
the rest uses the ``meta`` device, which behaves like an accelerator for placement checks.
"""

import copy

import pytest
import torch

from delta import losses as L
from delta.body.model import load_body_model
from delta.data.frames import load_frames, sample_rays
from delta.io import load_state
from delta.models.init import load_init
from delta.render.volume import stratified_samples
from delta.training.presets import resolve
from delta.training.run import build_avatar
from delta.training.trainer import _to, loss_terms

TINY = {"resolution": 32, "render": {"samples": 8}}


def test_samples_drawn_with_a_cpu_generator_are_the_same_on_another_device():
    near, far = torch.zeros(5), torch.linspace(1, 2, 5)
    cpu = stratified_samples(near, far, 6, True, torch.Generator().manual_seed(3))
    other = stratified_samples(near.to("meta"), far.to("meta"), 6, True, torch.Generator().manual_seed(3))
    assert other.device.type == "meta" and other.shape == cpu.shape
    again = stratified_samples(near, far, 6, True, torch.Generator().manual_seed(3))
    assert torch.equal(cpu, again)


@pytest.fixture(scope="module")
def tiny_avatar(tiny_training):
    inputs = tiny_training["tight"]
    st = resolve("fast", TINY)
    data = load_frames(inputs["record"], st.resolution, st.background, st.box_margin)
    body = load_body_model(inputs["body"])
    return build_avatar(body, st, load_init(inputs["init"], data), data, 1, torch.device("cpu")), data, st


@pytest.mark.slow
def test_moving_the_avatar_moves_its_body_model(tiny_avatar):
    model = copy.deepcopy(tiny_avatar[0]).to("meta")
    body = model.body
    assert body.v_template.device.type == "meta" and body.weights.device.type == "meta"
    assert body.faces.device.type == "meta" and model.poses.device.type == "meta"


def _step(model, batch, st, skin):
    """Loss terms and every parameter's gradient of one step of ``model`` (a copy is stepped)."""
    m = copy.deepcopy(model)
    terms, _ = loss_terms(m, batch, st, skin, generator=torch.Generator().manual_seed(1))
    L.total(terms, st.weights).backward()
    return {k: float(v.detach()) for k, v in terms.items()}, {
        n: p.grad for n, p in m.named_parameters() if p.grad is not None
    }


@pytest.mark.slow
def test_a_gpus_code_paths_give_the_cpus_losses_and_gradients(tiny_avatar, monkeypatch):
    """The step a GPU runs (tensor kNN and ray casting, flat leaf tests, the torch distance transform,
    grid_sample for the vertex fields), run on the CPU, against the CPU's own step (KD-tree, Embree or the
    binned search, SciPy, sparse matrices): the same losses and gradients up to float rounding."""
    from delta.devices import tensor_paths
    from delta.geometry import clusters, distance_grid

    model, data, st = tiny_avatar
    batch = sample_rays(data, int(data.train[0]), 256, torch.Generator().manual_seed(0))
    calls = {"flat": 0, "torch transform": 0}
    flat, transform = clusters._flat, distance_grid._transform_torch
    monkeypatch.setattr(clusters, "_flat", lambda *a: calls.__setitem__("flat", calls["flat"] + 1) or flat(*a))
    monkeypatch.setattr(distance_grid, "_transform_torch",
                        lambda *a, **k: calls.__setitem__("torch transform", 1) or transform(*a, **k))  # fmt: skip
    host = _step(model, batch, st, data.skin_color)
    assert calls == {"flat": 0, "torch transform": 0}
    with tensor_paths():
        gpu = _step(model, batch, st, data.skin_color)
    assert calls["flat"] > 0 and calls["torch transform"] == 1
    assert host[0].keys() == gpu[0].keys() and host[1].keys() == gpu[1].keys()
    for k, v in host[0].items():
        assert gpu[0][k] == pytest.approx(v, rel=1e-4, abs=1e-7), k
    for n, g in host[1].items():
        torch.testing.assert_close(gpu[1][n], g, rtol=1e-3, atol=1e-6, msg=n)


@pytest.mark.slow
def test_a_gpus_code_paths_render_the_cpus_image(tiny_avatar):
    """A whole image (the scoring render: chunks, supersampling where busy) on a GPU's code paths, on the
    CPU: the CPU's image up to float rounding, and the same pixels hit."""
    from delta.devices import tensor_paths
    from delta.models.image import render_image

    model, data, _ = tiny_avatar
    frame = int(data.train[0])
    with torch.no_grad():
        host = render_image(model, frame, supersample=2)
        with tensor_paths():
            gpu = render_image(model, frame, supersample=2)
    assert host.keys() == gpu.keys() and float(host["silhouette"].sum()) > 10
    for k, v in host.items():
        torch.testing.assert_close(gpu[k], v, rtol=1e-4, atol=1e-5, msg=k)


@pytest.mark.slow
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_losses_and_gradients_match_the_cpu(tiny_avatar):
    model, data, st = tiny_avatar
    batch = sample_rays(data, int(data.train[0]), 256, torch.Generator().manual_seed(0))
    out = {}
    for dev in ("cpu", "cuda"):
        m = copy.deepcopy(model).to(dev)
        terms, _ = loss_terms(m, _to(batch, torch.device(dev)), st, data.skin_color.to(dev),
                              generator=torch.Generator().manual_seed(1))  # fmt: skip
        L.total(terms, st.weights).backward()
        out[dev] = ({k: float(v) for k, v in terms.items()}, m.poses.grad.cpu())
    for k, v in out["cpu"][0].items():
        assert out["cuda"][0][k] == pytest.approx(v, rel=1e-4, abs=1e-7), k
    torch.testing.assert_close(out["cuda"][1], out["cpu"][1], rtol=1e-3, atol=1e-6)


@pytest.mark.slow
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_stage_interrupted_on_cuda_resumes_there(tiny_avatar, tmp_path):
    """The checkpoint is loaded with map_location=cuda, which moves the sampling generator's CPU state too."""
    from delta.training.trainer import CHECKPOINT, train_stage

    model, data, st = tiny_avatar
    st = copy.deepcopy(st)
    st.stage1.iterations = 4
    train_stage(1, copy.deepcopy(model).to("cuda"), data, st, tmp_path, max_steps=2)
    assert load_state(tmp_path / CHECKPOINT)["step"] == 2
    res = train_stage(1, copy.deepcopy(model).to("cuda"), data, st, tmp_path)
    assert res.steps == 4 and list(res.losses["step"]) == [1, 2, 3, 4]
