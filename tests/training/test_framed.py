"""The fields' boxes hold what the capture frames: a head-and-shoulders framing gets finer cells, no
exterior outside its box, and keeps its boxes through model.pt."""

import dataclasses

import pytest
import torch

from delta import DeltaError
from delta.body.lbs import lbs
from delta.body.model import load_body_model
from delta.data.frames import load_frames
from delta.fields.networks import NeRFField
from delta.io import load_state
from delta.models.init import load_init
from delta.scene.framing import framed_vertices
from delta.training.presets import resolve
from delta.training.run import build_avatar, load_trained, resolve_scope, save_model

pytestmark = pytest.mark.slow

TINY = {"resolution": 32, "render": {"samples": 8, "occupancy": {"enabled": False}}}


def _setup(inputs):
    st = resolve("fast", TINY)
    data = load_frames(inputs["record"], st.resolution, st.background, st.box_margin)
    return st, data, load_body_model(inputs["body"]), load_init(inputs["init"], data)


def _pinhole_inside(body, init, frame: int, n: int) -> torch.Tensor:
    """(V,) bool by the pinhole model written out: uv = K (R X + t) / z inside the n×n image, z > 0."""
    out = lbs(body, init.betas[None].float(), init.poses[frame : frame + 1].float(),
              transl=init.transl[frame : frame + 1].float())  # fmt: skip
    cam = init.camera
    x = out.vertices[0].double() @ cam.R.double().T + cam.t.double()
    uvw = x @ cam.K.double().T
    uv = uvw[:, :2] / uvw[:, 2:]
    return ((uv >= 0) & (uv < n)).all(-1) & (x[:, 2] > 0)


def _lowered(init, metres: float):
    low = init.transl.clone()
    low[:, 1] -= metres
    return dataclasses.replace(init, transl=low)


def test_framed_vertices_are_those_inside_some_frame(tiny_training):
    st, data, body, init = _setup(tiny_training["tight"])
    n = data.resolution
    args = (body, init.betas, init.poses)
    assert framed_vertices(*args, init.transl, init.camera, data.train, n).all()  # the whole body in view
    low = _lowered(init, 1.1)  # head and shoulders fill the frame
    framed = framed_vertices(*args, low.transl, init.camera, data.train, n)
    oracle = torch.zeros_like(framed)
    for k in data.train.tolist():
        oracle |= _pinhole_inside(body, low, k, n)
    assert torch.equal(framed, oracle)
    assert 0.05 < float(framed.float().mean()) < 0.9
    rest = body.v_template.float()
    assert float(rest[framed, 1].mean()) > float(rest[~framed, 1].mean()) + 0.4  # the top of the body


def test_the_fields_boxes_hold_the_framed_vertices(tiny_training):
    st, data, body, init = _setup(tiny_training["tight"])
    low = _lowered(init, 1.35)  # the head and the tops of the shoulders in view
    scope = resolve_scope(body, st, low, data)
    framed = scope["framed"]
    assert scope["capture"] == "upper" and not framed.all()
    part = build_avatar(body, st, low, data, 1, "cpu", scope)
    whole = build_avatar(body, st, low, data, 1, "cpu", dict(scope, framed=None))
    region = part.modelled & framed
    assert torch.equal(part.framed, region) and torch.equal(whole.framed, whole.modelled)
    template, cano = body.v_template.float(), part.canonical_vertices
    enc = part.albedo_field.encoding
    assert torch.allclose(enc.lo, template[region].amin(0) - 0.05) and torch.allclose(
        enc.hi, template[region].amax(0) + 0.05
    )
    margin = max(st.avatar.nerf_margin, st.avatar.render.max_dist)
    nerf = part.nerf.encoding
    assert torch.allclose(nerf.lo, cano[region].amin(0) - margin) and torch.allclose(
        nerf.hi, cano[region].amax(0) + margin
    )
    # the same number of cells over a smaller box: finer ones
    assert part.albedo_field.encoding.finest_cell() < 0.8 * whole.albedo_field.encoding.finest_cell()
    assert part.nerf.color_cell() < whole.nerf.color_cell()
    # no exterior outside the box; inside it, the field's own density
    assert part.nerf.bounded and not whole.nerf.bounded
    free = NeRFField(st.avatar.nerf, torch.stack([nerf.lo, nerf.hi]))
    free.load_state_dict(part.nerf.state_dict())
    g = torch.Generator().manual_seed(0)
    inside = nerf.lo + (nerf.hi - nerf.lo) * torch.rand(200, 3, generator=g)
    outside = inside - torch.tensor([0.0, 1.0, 0.0]) * (nerf.hi[1] - nerf.lo[1] + 0.01)
    with torch.no_grad():
        assert torch.equal(part.nerf.density(inside), free.density(inside))
        assert torch.equal(part.nerf(inside)[1], free(inside)[1])
        assert (free.density(outside) > 0).all()  # a grid's constant response beyond its box...
        assert (part.nerf.density(outside) == 0).all() and (part.nerf(outside)[1] == 0).all()  # ...is cut


def test_a_capture_that_frames_everything_builds_the_same_avatar(tiny_training):
    st, data, body, init = _setup(tiny_training["loose"])  # orthographic, the whole body in view
    scope = resolve_scope(body, st, init, data)
    assert scope["framed"].all()
    a = build_avatar(body, st, init, data, 1, "cpu", scope)
    b = build_avatar(body, st, init, data, 1, "cpu", dict(scope, framed=None))
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not a.nerf.bounded


def test_model_pt_keeps_the_framed_vertices(tiny_training, tmp_path):
    inputs = tiny_training["tight"]
    st, data, body, init = _setup(inputs)
    low = _lowered(init, 1.1)
    scope = resolve_scope(body, st, low, data)
    model = build_avatar(body, st, low, data, 1, "cpu", scope)
    save_model(tmp_path / "model.pt", model, 1, "fast", st, 0)
    back = load_trained(tmp_path / "model.pt", inputs["record"], inputs["body"]).model
    assert torch.equal(back.framed, model.framed) and back.nerf.bounded
    assert torch.equal(back.nerf.encoding.lo, model.nerf.encoding.lo)
    # a mask that is not the body model's, or not a mask at all: the file is named
    for bad, what in ((model.framed[:-5].clone(), "vertices"), ([1, 0], "per-vertex mask")):
        state = load_state(tmp_path / "model.pt")
        state["framed"] = bad
        torch.save(state, tmp_path / "bad.pt")
        with pytest.raises(DeltaError, match=f"bad.pt.*{what}"):
            load_trained(tmp_path / "bad.pt", inputs["record"], inputs["body"])
    # a file from before the framed vertices were kept: its boxes hold every modelled vertex
    old = build_avatar(body, st, low, data, 1, "cpu", dict(scope, framed=None))
    save_model(tmp_path / "old.pt", old, 1, "fast", st, 0)
    state = load_state(tmp_path / "old.pt")
    del state["framed"]
    torch.save(state, tmp_path / "old.pt")
    back = load_trained(tmp_path / "old.pt", inputs["record"], inputs["body"]).model
    assert torch.equal(back.framed, back.modelled) and not back.nerf.bounded
    template = body.v_template.float()  # its vertex fields over the whole template, as such files were trained
    assert torch.allclose(back.albedo_field.encoding.lo, template.amin(0) - 0.05)
    assert torch.allclose(back.nerf.encoding.lo, back.canonical_vertices[back.modelled].amin(0) - st.avatar.nerf_margin)
