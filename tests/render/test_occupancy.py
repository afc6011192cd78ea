"""The canonical occupancy grid: which cells it marks, and that skipping samples changes nothing they held."""

import pytest
import torch

from delta.render.hybrid import render_rays
from delta.render.settings import RenderSettings
from delta.render.occupancy import OccupancyGrid
from delta.render.settings import OccupancySettings
from tests.conftest import upsampled
from tests.render.test_hybrid import BG, sphere_avatar

BOX = torch.tensor([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])
SLAB = 0.1  # a cell boundary of the 10-cell grid over BOX


def slab_density(x: torch.Tensor, sigma: float = 40.0) -> torch.Tensor:
    """σ where x > SLAB (aligned with cell boundaries), exactly 0 elsewhere."""
    return torch.where(x[:, 0] > SLAB, torch.full_like(x[:, 0], sigma), torch.zeros_like(x[:, 0]))


def grid(**kw) -> OccupancyGrid:
    return OccupancyGrid(BOX, OccupancySettings(enabled=True, resolution=10, **kw))


def test_known_density_marks_exactly_its_cells():
    g = grid(threshold=1.0)
    assert g.shape == (10, 10, 10) and not bool(g.active) and g.occupied.all()
    g.update(slab_density, seed=3)
    expected = torch.zeros(10, 10, 10, dtype=torch.bool)
    expected[6:] = True  # cells [0.1, 0.2], ..., [0.4, 0.5] along x
    assert bool(g.active) and torch.equal(g.occupied, expected)
    assert g.fraction() == 0.4
    pts = torch.tensor([[0.15, 0.0, 0.0], [0.05, 0.3, -0.2], [0.45, -0.45, 0.45], [2.0, 0.0, 0.0]])
    assert g.contains(pts).tolist() == [True, False, True, True]  # outside the box: never skipped


def test_occupancy_decays_before_a_cell_is_freed():
    g = grid(threshold=1.0, decay=0.5)
    g.update(lambda x: torch.full_like(x[:, 0], 10.0), seed=0)
    occupied = []
    for step in range(1, 5):  # the density at x < SLAB has vanished: kept maxima 5, 2.5, 1.25, 0.625
        g.update(lambda x: slab_density(x, 10.0), seed=step)
        occupied.append(g.fraction())
    assert occupied == [1.0, 1.0, 1.0, 0.4]
    assert torch.allclose(g.density[:6], torch.full((6, 10, 10), 0.625))


def test_a_nearly_uniform_field_keeps_its_denser_cells():
    """Below the threshold everywhere (early training), the cells above the mean stay occupied."""
    g = grid(threshold=1.0)
    g.update(lambda x: 0.1 + 0.01 * (x[:, 0] > SLAB).float(), seed=0)
    assert g.fraction() == 0.4 and g.occupied[6:].all()
    g.update(lambda x: torch.full_like(x[:, 0], 0.1), seed=1)  # max(0.95 · 0.11, 0.1) = 0.1045 vs 0.1
    assert g.fraction() == 0.4


def test_a_field_that_collapsed_to_zero_keeps_every_cell():
    """σ = 0 everywhere (exp underflow) must not empty the grid: no sample would reach the NeRF again."""
    g = grid(threshold=1.0)
    g.update(lambda x: torch.zeros_like(x[:, 0]), seed=0)
    assert bool(g.active) and g.fraction() == 1.0
    g.update(slab_density, seed=1)  # once the field has structure again, the grid follows it
    assert g.fraction() == 0.4


def test_dilation_grows_the_occupied_set_by_whole_cells():
    g = OccupancyGrid(BOX, OccupancySettings(enabled=True, resolution=10, threshold=1.0), dilation=0.05)
    g.update(slab_density, seed=1)
    assert g.dilation == 1 and g.occupied[5:].all() and not g.occupied[:5].any()


def test_grow_tests_against_the_occupied_set_grown_by_whole_cells():
    g = grid(threshold=1.0)
    g.update(slab_density, seed=1)  # cells 6..9 along x (x > 0.1)
    x = torch.tensor([[0.15, 0.0, 0.0], [0.05, 0.0, 0.0], [-0.05, 0.0, 0.0], [0.9, 0.0, 0.0]])
    assert g.contains(x).tolist() == [True, False, False, True]  # outside the box: never skipped
    assert g.contains(x, grow=1).tolist() == [True, True, False, True]
    assert g.contains(x, grow=2).tolist() == [True, True, True, True]
    assert g.occupied[:6].sum() == 0  # the grid itself is unchanged


def test_the_grown_set_follows_updates_and_loaded_state():
    g = grid(threshold=1.0)
    g.update(slab_density, seed=1)  # cells 6..9 along x
    x = torch.tensor([[0.05, 0.0, 0.0], [-0.45, 0.0, 0.0]])
    assert g.contains(x, grow=1).tolist() == [True, False]
    g.update(lambda p: 5.0 * (p[:, 0] < -0.4).float(), seed=2)  # decay 0.95: the slab stays, cell 0 joins
    assert g.contains(x, grow=1).tolist() == [True, True]
    other = grid(threshold=1.0)
    other.update(lambda p: 5.0 * (p[:, 0] < -0.4).float(), seed=3)  # cell 0 only
    g.load_state_dict(other.state_dict())
    assert g.contains(x, grow=1).tolist() == [False, True]


def test_carry_over_regrows_the_loaded_grid_by_its_own_dilation():
    stage1 = grid(threshold=1.0)
    assert stage1.carry_over() is False and stage1.occupied.all()  # never updated: nothing to carry
    stage1.update(slab_density, seed=1)  # cells 6..9 along x
    stage2 = OccupancyGrid(BOX, OccupancySettings(enabled=True, resolution=10, threshold=1.0), dilation=0.15)
    stage2.load_state_dict(stage1.state_dict())
    assert stage2.carry_over() is True and stage2.dilation == 2
    assert bool(stage2.active) and torch.equal(stage2.density, stage1.density)
    assert stage2.occupied[4:].all() and not stage2.occupied[:4].any()


def test_an_early_update_keeps_the_body_shell_a_later_one_does_not():
    """Before the warm-up's end the cells within ``early_shell`` of the body stay occupied whatever the young
    field's density there; the empty space beyond them and the slab are marked from the density."""
    body = torch.tensor([[-0.35, 0.0, 0.0], [-0.25, 0.0, 0.0]])  # in cells 1 and 2 along x, 5 along y and z
    g = OccupancyGrid(BOX, OccupancySettings(enabled=True, resolution=10, threshold=1.0, early=2, warmup=4,
                                             early_shell=0.1), body=body)  # fmt: skip
    assert g.shell.sum() == 4 * 3 * 3  # cells 0-3 along x, 4-6 along y and z: one cell (0.1 m) around each
    assert g.shell_reach == pytest.approx(0.2)  # a vertex's own cell and one more
    assert torch.equal(g.shell[:, 5, 5], torch.tensor([True] * 4 + [False] * 6))
    g.update(slab_density, seed=0, early=True)
    slab = torch.zeros(10, 10, 10, dtype=torch.bool)
    slab[6:] = True
    assert torch.equal(g.occupied, slab | g.shell) and 0.4 < g.fraction() < 1
    assert g.contains(torch.tensor([[-0.3, 0.0, 0.0], [-0.3, 0.4, 0.0]])).tolist() == [True, False]
    g.update(slab_density, seed=1)  # the warm-up is over: the density alone
    assert torch.equal(g.occupied, slab)


def test_without_early_updates_the_shell_is_empty_and_not_saved():
    body = torch.zeros(1, 3)
    g = OccupancyGrid(BOX, OccupancySettings(enabled=True, resolution=10, threshold=1.0), body=body)
    assert not g.shell.any() and "shell" not in g.state_dict()
    g.update(slab_density, seed=0, early=True)
    assert g.fraction() == 0.4


def test_reset_forgets_everything():
    g = grid()
    g.update(slab_density, seed=0)
    g.reset()
    assert not bool(g.active) and g.occupied.all() and (g.density == 0).all()


def _nerf(a: torch.Tensor, b: torch.Tensor, calls: list):
    def nerf(x):
        calls.append(len(x))
        sigma = a * slab_density(x, 1.0)
        sigma = torch.where(x.norm(dim=-1) < 0.3 - 1e-3, torch.full_like(sigma, 1e6), sigma)
        return torch.sigmoid(b * x), sigma

    return nerf


def _render(occupied, a, b, calls, early_cull=True):
    mesh = sphere_avatar()
    o = torch.tensor([[x, 0.0, 2.0] for x in (-0.32, -0.1, 0.05, 0.15, 0.33, 0.36)])
    d = torch.tensor([[0.0, 0.0, -1.0]] * len(o))
    st = RenderSettings(samples=24, box_margin=0.3, max_dist=0.1, perturb=False, early_cull=early_cull)
    return render_rays(mesh, o, d, o[:, :2] * 100, BG, st, _nerf(a, b, calls), occupied=occupied)


def test_all_occupied_renders_exactly_as_without_a_grid():
    a, b = torch.tensor(30.0), torch.tensor([1.0, 2.0, 3.0])
    g = grid()
    g.update(lambda x: torch.full_like(x[:, 0], 5.0), seed=0)
    plain, culled = _render(None, a, b, []), _render(g.contains, a, b, [])
    assert plain.samples_evaluated == culled.samples_evaluated > 0
    assert torch.equal(plain.rgb, culled.rgb) and torch.equal(plain.nerf_mask, culled.nerf_mask)


def test_skipping_empty_cells_keeps_colour_and_gradients():
    a0, b0 = torch.tensor(30.0), torch.tensor([1.0, 2.0, 3.0])
    g = grid(threshold=0.5)
    g.update(lambda x: slab_density(x) + 1e6 * (x.norm(dim=-1) < 0.3).float(), seed=0)
    out = {}
    for name, occ in (("plain", None), ("culled", g.contains)):
        a, b = a0.clone().requires_grad_(), b0.clone().requires_grad_()
        r = _render(occ, a, b, [])
        (r.rgb * torch.tensor([1.0, 2.0, 3.0])).sum().backward()
        out[name] = (r, a.grad, b.grad)
    (p, pa, pb), (c, ca, cb) = out["plain"], out["culled"]
    assert 0 < c.samples_evaluated < p.samples_evaluated  # empty cells were skipped ...
    assert 0 < float(p.nerf_mask.detach().max()) < 1
    torch.testing.assert_close(c.rgb, p.rgb, atol=1e-6, rtol=0)  # ... and held nothing
    torch.testing.assert_close(c.nerf_mask, p.nerf_mask, atol=1e-6, rtol=0)
    assert pa.abs() > 0 and pb.abs().sum() > 0
    torch.testing.assert_close(ca, pa, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(cb, pb, rtol=1e-5, atol=1e-7)


def test_a_grid_that_is_wrong_changes_the_render():
    """The check is real: a grid marking the dense slab empty removes its colour."""
    a, b = torch.tensor(30.0), torch.tensor([1.0, 2.0, 3.0])
    g = grid(threshold=0.5)
    g.update(lambda x: 1e6 * (x.norm(dim=-1) < 0.3).float(), seed=0)  # sees the body only
    plain, culled = _render(None, a, b, []), _render(g.contains, a, b, [])
    assert float((plain.nerf_mask - culled.nerf_mask).abs().max()) > 0.1


def test_early_cull_skips_the_knn_query_for_empty_cells_and_changes_nothing(monkeypatch):
    """Identity skinning: the rough canonical point is exact, so the early cull drops just the samples
    the exact tests would (grown by a cell), before the kNN query, and the render is unchanged."""
    from delta.render import hybrid

    queried = []
    deform = hybrid.deformer.deform
    monkeypatch.setattr(hybrid.deformer, "deform", lambda frame, x, *a: queried.append(len(x)) or deform(frame, x, *a))
    a0, b0 = torch.tensor(30.0), torch.tensor([1.0, 2.0, 3.0])
    g = grid(threshold=0.5)
    g.update(lambda x: slab_density(x) + 1e6 * (x.norm(dim=-1) < 0.3).float(), seed=0)
    out = {}
    for early in (False, True):
        a, b = a0.clone().requires_grad_(), b0.clone().requires_grad_()
        r = _render(g.contains, a, b, [], early_cull=early)
        (r.rgb * torch.tensor([1.0, 2.0, 3.0])).sum().backward()
        out[early] = (r, a.grad, b.grad)
    (late, la, lb), (early, ea, eb) = out[False], out[True]
    assert 0 < queried[1] < queried[0]  # fewer samples reach the kNN query ...
    assert early.samples_evaluated == late.samples_evaluated > 0  # ... and the same ones reach the NeRF
    assert torch.equal(early.rgb, late.rgb) and torch.equal(early.nerf_mask, late.nerf_mask)
    assert torch.equal(ea, la) and torch.equal(eb, lb)


@pytest.mark.parametrize("bend, most_lost", [(0.1, 0.002), (0.3, 0.02)])
def test_early_cull_loses_few_samples_the_exact_tests_keep_on_a_posed_anny(anny_files, bend, most_lost):
    """The real body (upsampled Anny, the avatar's kNN vertices) in a random pose (``bend`` rad per joint
    around the canonical pose), the fast preset's 3-cm occupancy cells over a canonical region cutting
    across limbs. The early cull drops most samples; of those the exact tests keep it loses only some
    where body parts touch (fingers, a hand on a thigh): there the kNN blend of the parts' maps lands
    between them, more than a cell from any one vertex's map. The loose capture's own poses lose none
    in stage 1 and 0.04 % in stage 2 (benchmarks/early_cull.csv)."""
    from delta.body.lbs import lbs
    from delta.deformers import knn as deformer
    from delta.models.avatar import knn_vertex_ids
    from delta.render.hybrid import early_cull

    body = upsampled(anny_files["body"])
    ids = knn_vertex_ids(body, "base")
    gen = torch.Generator().manual_seed(3)
    pose = body.canonical_pose[None].float() + bend * torch.randn(1, body.num_joints, 3, generator=gen)
    out = lbs(body, torch.zeros(1, 1), pose)
    cano = lbs(body, torch.zeros(1, 1), body.canonical_pose[None].float())
    frame = deformer.prepare(out.vertices[0, ids], out.vertex_transforms_3x4[0, ids],
                             out.rest_vertices[0, ids] - body.v_template[ids], cano.vertex_transforms_3x4[0, ids],
                             body.weights[ids], near_cell=0.02, near_pad=0.14)  # fmt: skip
    cv = cano.vertices[0]
    occ = OccupancyGrid(
        torch.stack([cv.amin(0) - 0.3, cv.amax(0) + 0.3]), OccupancySettings(enabled=True, resolution=64)
    )
    # occupied: a shell 2-8 cm from the canonical body on the +x side of a tilted plane (cuts the limbs)
    tree = deformer.prepare(cv[ids], cano.vertex_transforms_3x4[0, ids], torch.zeros_like(cv[ids]),
                            cano.vertex_transforms_3x4[0, ids], body.weights[ids]).index  # fmt: skip
    occ.update(lambda x: 5.0 * (((d := tree.query(x, 1)[0][:, 0]) > 0.02) & (d < 0.08)).float()
               * (x @ torch.tensor([1.0, 0.3, 0.2]) > 0).float(), seed=0)  # fmt: skip
    posed = frame.posed
    x = posed[torch.randint(len(posed), (60000,), generator=gen)] + 0.1 * torch.randn(60000, 3, generator=gen)
    d = deformer.deform(frame, x, 6, 0.1, 0.1)
    exact = d.valid & occ.contains(d.canonical)
    early = early_cull(frame, x, 0.1, occ.contains)
    assert int(exact.sum()) > 2000 and int(early.sum()) < 0.6 * len(x)  # both act
    assert int((exact & ~early).sum()) <= most_lost * int(exact.sum())


def test_a_settled_point_meets_the_occupied_set_without_the_dilation():
    g = OccupancyGrid(BOX, OccupancySettings(enabled=True, resolution=10, threshold=1.0), dilation=0.05)
    g.update(slab_density, seed=1)  # cells 6..9 along x, grown by one cell for the test before F_e
    x = torch.tensor([[0.15, 0.0, 0.0], [0.05, 0.0, 0.0], [-0.05, 0.0, 0.0], [0.9, 0.0, 0.0]])
    assert g.contains(x).tolist() == [True, True, False, True]
    assert g.contains(x, settled=True).tolist() == [True, False, False, True]
    assert g.contains(x, grow=1, settled=True).tolist() == [True, True, False, True]
    other = grid(threshold=1.0)
    other.update(lambda p: 5.0 * (p[:, 0] < -0.4).float(), seed=3)  # cell 0 only
    g.load_state_dict(other.state_dict())  # the loaded densities decide, not a cached set
    assert g.contains(torch.tensor([[-0.45, 0.0, 0.0], [0.15, 0.0, 0.0]]), settled=True).tolist() == [True, False]
    flat = grid(threshold=1.0)
    flat.update(lambda p: torch.zeros_like(p[:, 0]), seed=0)  # a collapsed field keeps every cell here too
    assert flat.contains(x, settled=True).all()


def test_points_F_e_moves_into_empty_cells_skip_the_nerf_and_change_nothing():
    """F_e shifts every point 0.08 m along -x; the grid (dilated by F_e's 0.1-m reach) holds the slab
    and the body. The NeRF sees only points that land in the slab's or the body's cells, and the
    render and its gradients are those without a grid, whose NeRF is exactly 0 elsewhere."""
    g = OccupancyGrid(BOX, OccupancySettings(enabled=True, resolution=10, threshold=0.5), dilation=0.1)
    g.update(lambda x: slab_density(x) + 1e6 * (x.norm(dim=-1) < 0.3).float(), seed=0)
    shift = torch.tensor([-0.08, 0.0, 0.0])
    seen, out = [], {}
    for name, occ in (("plain", None), ("culled", g.contains)):
        a, b = torch.tensor(30.0, requires_grad=True), torch.tensor([1.0, 2.0, 3.0], requires_grad=True)
        nerf = _nerf(a, b, [])
        r = render_rays(*_scene(), nerf=lambda x: seen.append((name, x.detach())) or nerf(x),
                        nonrigid=lambda x, ref: shift.expand_as(x), occupied=occ)  # fmt: skip
        (r.rgb * torch.tensor([1.0, 2.0, 3.0])).sum().backward()
        out[name] = (r, a.grad, b.grad)
    (p, pa, pb), (c, ca, cb) = out["plain"], out["culled"]
    culled_points = torch.cat([x for name, x in seen if name == "culled"])
    assert g.contains(culled_points, settled=True).all()
    assert not g.contains(torch.cat([x for name, x in seen if name == "plain"]), settled=True).all()
    assert 0 < c.samples_evaluated < p.samples_evaluated and float(p.nerf_mask.detach().max()) > 0.1
    torch.testing.assert_close(c.rgb, p.rgb, atol=1e-6, rtol=0)
    torch.testing.assert_close(ca, pa, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(cb, pb, rtol=1e-5, atol=1e-7)


def _scene():
    mesh = sphere_avatar()
    o = torch.tensor([[x, 0.0, 2.0] for x in (-0.32, -0.1, 0.05, 0.15, 0.22, 0.33, 0.36)])
    d = torch.tensor([[0.0, 0.0, -1.0]] * len(o))
    st = RenderSettings(samples=24, box_margin=0.3, max_dist=0.1, perturb=False)
    return mesh, o, d, o[:, :2] * 100, BG, st
