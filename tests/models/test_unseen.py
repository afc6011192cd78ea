"""The albedo where no training frame looked: which vertices a capture sees, the fill in their place, and the
fill carried through model.pt."""

import numpy as np
import pytest
import torch

from delta import DeltaError
from delta.body.model import REGION
from delta.geometry.sight import vertex_normals
from delta.models.unseen import FACING, seen_vertices, spread, unseen_albedo
from delta.training.presets import resolve
from delta.training.run import load_trained


@pytest.fixture(scope="module")
def trained(tiny_trained):
    t = tiny_trained["tight"]
    return load_trained(t["model"], t["record"], t["body"])


def test_one_frame_sees_no_vertex_turned_away_and_more_frames_see_more(trained):
    model, train = trained.model, trained.data.train
    one = seen_vertices(model, train[:1])
    every = seen_vertices(model, train)
    assert bool((every | one).eq(every).all()) and int(every.sum()) > int(one.sum()) > 0  # a superset, larger
    verts = model.pose_body(int(train[0]), model.offsets()).vertices[0].detach().double()
    cam = model.camera(int(train[0]))
    towards = cam.center.double() - verts  # the pinhole subject: from each vertex to the camera
    cos = (vertex_normals(verts, model.body.faces) * towards / towards.norm(dim=-1, keepdim=True)).sum(-1)
    assert not bool(one[cos <= FACING].any())  # turned away, or grazing: not seen
    assert float(one[cos > 0.9].float().mean()) > 0.5  # most of what faces the camera squarely is seen


def test_the_fill_takes_the_unseen_vertices_only_and_stays_within_the_seen_colours(trained):
    model, train = trained.model, trained.data.train
    model.fill_albedo(torch.zeros(0, dtype=torch.int64), torch.zeros(0, 3))
    field = model.albedo().detach()
    ids, values, evidence = unseen_albedo(model, train[:1], outside=False)
    seen = seen_vertices(model, train[:1])
    mouth = model.body.regions == REGION["mouth"]
    expected = torch.nonzero(~seen & ~mouth).squeeze(1)
    assert torch.equal(ids, expected) and evidence["filled"] == len(ids) > 0
    assert evidence["seen"] == int(seen.sum()) and evidence["frames_looked"] == 1
    lo, hi = field[seen].amin(0), field[seen].amax(0)
    assert bool(((values >= lo - 1e-5) & (values <= hi + 1e-5)).all())
    model.fill_albedo(ids, values)
    now = model.albedo().detach()
    assert torch.equal(now[ids], values) and torch.equal(now[~torch.isin(torch.arange(len(now)), ids)],
                                                         field[~torch.isin(torch.arange(len(now)), ids)])  # fmt: skip
    assert not bool(mouth[ids].any())


def test_the_field_still_learns_beside_a_fill(trained):
    model = trained.model
    ids = torch.arange(0, model.body.num_vertices, 2)
    model.fill_albedo(ids, torch.full((len(ids), 3), 0.5))
    model.albedo().sum().backward()
    grads = [p.grad for p in model.albedo_field.parameters() if p.grad is not None]
    assert grads and any(bool(g.abs().sum() > 0) for g in grads)
    model.zero_grad()
    with pytest.raises(ValueError, match="albedo fill"):
        model.fill_albedo(torch.tensor([model.body.num_vertices]), torch.zeros(1, 3))
    with pytest.raises(ValueError, match="albedo fill"):
        model.fill_albedo(torch.tensor([0, 1]), torch.zeros(1, 3))


def test_a_trained_model_carries_its_fill(tiny_trained):
    t = tiny_trained["tight"]
    state = torch.load(t["model"], weights_only=True)
    fill = state["albedo_fill"]
    model = load_trained(t["model"], t["record"], t["body"]).model
    assert len(fill["ids"]) > 0 and torch.equal(model.fill_ids, fill["ids"])
    torch.testing.assert_close(model.albedo().detach()[fill["ids"]], fill["values"])
    again = unseen_albedo(model, load_trained(t["model"], t["record"], t["body"]).data.train)
    assert torch.equal(again[0], fill["ids"])  # the same frames see the same vertices


def test_frames_are_spread_evenly_up_to_the_most():
    np.testing.assert_array_equal(spread(np.arange(10), 20), np.arange(10))
    got = spread(np.arange(100, 400), 4)
    np.testing.assert_array_equal(got, [100, 200, 299, 399])


def test_the_setting_takes_outside_fill_or_field():
    assert resolve("fast").unseen_albedo == "outside"
    assert [resolve("fast", {"unseen_albedo": v}).unseen_albedo for v in ("fill", "field")] == ["fill", "field"]
    with pytest.raises(DeltaError, match="training.unseen_albedo"):
        resolve("fast", {"unseen_albedo": "mirror"})


def test_the_exterior_is_mirrored_where_no_frame_looked_and_only_where_its_line_holds_exterior(trained, monkeypatch):
    import delta.models.unseen as unseen

    model, train = trained.model, trained.data.train
    monkeypatch.setattr(unseen, "_holds", lambda m, p: torch.ones(len(p), dtype=torch.bool))  # exterior everywhere
    one, ev_one = unseen.exterior_mirror(model, train[:1])
    every, ev_every = unseen.exterior_mirror(model, train)
    assert one is not None and ev_one["mirrored"] == int(one.planes.isfinite().sum()) > 0
    assert ev_every["seen"] > ev_one["seen"] and ev_every["mirrored"] < ev_one["mirrored"]
    # each mirrored cell's centre and its image lie on opposite sides of the body along z, as far from it
    lo, cell = one.lo.double(), one.cell
    at = torch.nonzero(one.planes.isfinite())
    z = lo[2] + cell * (at[:, 2].double() + 0.5)
    image = one.planes[at[:, 0], at[:, 1], at[:, 2]].double() - z
    cano = model.canonical_vertices.detach().double()
    assert bool(((image - z).abs() > 0).all())
    assert float(z.min()) < float(cano[:, 2].max()) and float(image.max()) > float(cano[:, 2].min())
    monkeypatch.setattr(unseen, "_holds", lambda m, p: torch.zeros(len(p), dtype=torch.bool))  # no exterior
    assert unseen.exterior_mirror(model, train[:1])[0] is None


def test_a_mirror_travels_through_model_pt():
    grid = torch.full((3, 4, 5), float("nan"))
    grid[1, 2, 3] = 0.25
    from delta.geometry.mirror import MirrorGrid
    from delta.models.unseen import mirror_from_state, mirror_state

    back = mirror_from_state(mirror_state(MirrorGrid(torch.tensor([0.0, 1.0, 2.0]), 0.02, grid)))
    assert back.cell == 0.02 and torch.equal(back.lo, torch.tensor([0.0, 1.0, 2.0]))
    assert torch.equal(back.planes.isnan(), grid.isnan()) and float(back.planes[1, 2, 3]) == 0.25
    assert mirror_state(None) is None and mirror_from_state(None) is None
    with pytest.raises(ValueError, match="exterior_mirror"):
        mirror_from_state({"lo": torch.zeros(3), "cell": 0.02, "planes": torch.zeros(4)})


def test_one_pass_over_the_frames_gives_what_the_fill_and_the_mirror_give_alone(trained, monkeypatch):
    import delta.models.unseen as unseen

    model, train = trained.model, trained.data.train
    model.fill_albedo(torch.zeros(0, dtype=torch.int64), torch.zeros(0, 3))
    monkeypatch.setattr(unseen, "_holds", lambda m, p: torch.ones(len(p), dtype=torch.bool))
    (ids, values), mirror, evidence = unseen.unseen_parts(model, train[:2])
    alone_ids, alone_values, _ = unseen.unseen_albedo(model, train[:2])
    alone_mirror, _ = unseen.exterior_mirror(model, train[:2])
    assert torch.equal(ids, alone_ids) and torch.equal(values, alone_values)
    assert torch.equal(mirror.planes.isnan(), alone_mirror.planes.isnan())
    torch.testing.assert_close(mirror.planes.nan_to_num(), alone_mirror.planes.nan_to_num())
    assert evidence["albedo"]["filled"] == len(ids) and evidence["exterior"]["mirrored"] > 0
    (none_ids, _), none_mirror, _ = unseen.unseen_parts(model, train[:2], albedo=False, exterior=False)
    assert len(none_ids) == 0 and none_mirror is None


class _Slab(torch.nn.Module):
    """A stand-in exterior: colour ``color`` and density ``sigma`` wherever ``where`` holds (everywhere: None)."""

    def __init__(self, color, sigma: float, where=None):
        super().__init__()
        self.color, self.sigma, self.where = torch.tensor(color), sigma, where

    def forward(self, x):
        s = torch.full((len(x),), self.sigma)
        if self.where is not None:
            s = torch.where(self.where(x), s, torch.zeros_like(s))
        return self.color.expand(len(x), 3), s


def test_the_look_from_outside_is_the_exterior_composited_over_the_albedo(trained, monkeypatch):
    import delta.models.unseen as unseen

    model = trained.model
    model.fill_albedo(torch.zeros(0, dtype=torch.int64), torch.zeros(0, 3))
    ids = torch.arange(0, model.body.num_vertices, 97)
    albedo = model.albedo().detach()[ids]
    reach = float(model.spec.render.max_dist)
    monkeypatch.setattr(model, "occupancy", None)
    for sigma in (0.0, 5.0, 40.0, 1e4):
        monkeypatch.setattr(model, "nerf", _Slab([0.1, 0.7, 0.3], sigma))
        cover = 1 - np.exp(-sigma * reach)  # a constant density along the normal: exact at any sample count
        expected = cover * torch.tensor([0.1, 0.7, 0.3]) + (1 - cover) * albedo
        torch.testing.assert_close(unseen.outside_look(model, ids), expected, atol=1e-5, rtol=1e-5)
    # an exterior beyond the reach covers nothing; one behind the surface (inside the body) neither
    cano = model.canonical_vertices.detach()
    normals = vertex_normals(cano, model.body.faces)
    far = lambda x: torch.cdist(x, cano[ids].float()).amin(1) > reach  # noqa: E731
    monkeypatch.setattr(model, "nerf", _Slab([0.1, 0.7, 0.3], 1e4, far))
    torch.testing.assert_close(unseen.outside_look(model, ids), albedo)
    assert float(normals[ids].norm(dim=-1).min()) > 0.99


def test_a_covered_border_lends_its_look_to_the_unseen_vertices(trained, monkeypatch):
    """Every seen vertex beside an unseen one under an opaque exterior of one colour: each filled vertex that
    reaches such a border takes that colour (the harmonic fill of a constant), and the albedo-only fill does
    not."""
    import delta.models.unseen as unseen

    model, train = trained.model, trained.data.train
    model.fill_albedo(torch.zeros(0, dtype=torch.int64), torch.zeros(0, 3))
    monkeypatch.setattr(model, "occupancy", None)
    monkeypatch.setattr(model, "nerf", _Slab([0.1, 0.7, 0.3], 1e4))
    ids, values, evidence = unseen.unseen_albedo(model, train[:1])
    assert len(ids) > 0 and evidence["border_covered"] > 0
    torch.testing.assert_close(values, torch.tensor([0.1, 0.7, 0.3]).expand_as(values), atol=1e-4, rtol=0)
    _, plain, plain_evidence = unseen.unseen_albedo(model, train[:1], outside=False)
    assert "border_covered" not in plain_evidence and float((plain - values).abs().max()) > 0.1
