"""Rendering rays through the hybrid avatar: culling far from the body, the mesh stop, misses."""

import dataclasses
import math

import torch
import trimesh

from delta.deformers import knn as deformer
from delta.render.hybrid import PosedMesh, render_rays
from delta.render.settings import RenderSettings

BG = torch.tensor([1.0, 1.0, 1.0])
MESH_RGB = torch.tensor([0.2, 0.4, 0.6])
NERF_RGB = torch.tensor([0.9, 0.1, 0.1])


def sphere_avatar(radius=0.3):
    """A sphere 'body' posed with identity transforms (posed space = canonical space)."""
    s = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    v = torch.tensor(s.vertices, dtype=torch.float32)
    f = torch.tensor(s.faces, dtype=torch.int64)
    eye = torch.eye(3, 4).expand(len(v), 3, 4)
    skin = deformer.prepare(v, eye, torch.zeros_like(v), eye, torch.ones(len(v), 1), near_cell=0.01, near_pad=0.2)
    uv = v[:, :2] * 100  # any projection: the silhouette is not under test here
    return PosedMesh(v, f, MESH_RGB.expand(len(v), 3), uv, skin)


def shell_nerf(radius, thickness, sigma):
    """Density ``sigma`` in a shell just outside the sphere, everywhere beyond it too (to catch leaks)."""
    calls = []

    def nerf(x):
        calls.append(len(x))
        r = x.norm(dim=-1)
        dens = torch.where(r > radius, torch.full_like(r, sigma), torch.zeros_like(r))
        dens = torch.where(r < radius - 1e-3, torch.full_like(r, 1e6), dens)  # inside the body: must never be seen
        return NERF_RGB.expand(len(x), 3), dens

    return nerf, calls


def rays(offsets):
    """Rays along -z at x offsets from the sphere's axis, starting at z = 2."""
    o = torch.tensor([[x, 0.0, 2.0] for x in offsets])
    d = torch.tensor([[0.0, 0.0, -1.0]] * len(offsets))
    return o, d


def render(offsets, sigma=0.0, max_dist=0.1):
    mesh = sphere_avatar()
    nerf, calls = shell_nerf(0.3, 0.05, sigma)
    o, d = rays(offsets)
    st = RenderSettings(samples=16, box_margin=0.3, max_dist=max_dist, perturb=False)
    out = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, nerf)
    return out, calls


def test_rays_far_from_the_body_cost_nothing_and_show_the_background():
    out, calls = render([0.55, 0.8], sigma=50.0)  # 0.25 m and 0.5 m from the surface, max_dist 0.1
    assert not out.hit.any()
    assert out.samples_evaluated == 0 and sum(calls) == 0
    torch.testing.assert_close(out.rgb, BG.expand(2, 3))
    assert (out.nerf_mask == 0).all()


def test_a_ray_hitting_the_mesh_ends_there():
    out, _ = render([0.0], sigma=0.0)
    assert out.hit.all()
    torch.testing.assert_close(out.rgb, MESH_RGB[None])  # no density: all transmittance reaches the mesh


def test_nothing_behind_the_mesh_contributes():
    # huge density everywhere inside the sphere; the ray stops at the surface, so none of it is seen
    out, calls = render([0.0, 0.1], sigma=0.0)
    assert out.hit.all() and sum(calls) > 0
    torch.testing.assert_close(out.rgb, MESH_RGB.expand(2, 3))


def test_through_the_mesh_the_nerf_alone_is_rendered():
    """SCARF's NeRF-only stage: a ray that hits the body does not stop there; what lies inside it
    (here 1e6, never seen when rays stop) is rendered, over the background, not the mesh colour."""
    mesh = sphere_avatar()
    o, d = rays([0.0, 0.1, 0.55])
    st = RenderSettings(samples=16, box_margin=0.3, max_dist=0.1, perturb=False)
    out = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, shell_nerf(0.3, 0.05, 0.0)[0], through_mesh=True)
    assert out.hit[:2].all() and not out.hit[2]
    torch.testing.assert_close(out.mesh_rgb[:2], MESH_RGB.expand(2, 3))  # still returned for the mesh terms
    torch.testing.assert_close(out.rgb[:2], NERF_RGB.expand(2, 3), atol=1e-3, rtol=0)  # the 1e6 interior
    assert (out.nerf_mask[:2] > 0.999).all()
    torch.testing.assert_close(out.rgb[2], BG)  # 0.25 m from the body: empty
    empty = lambda x: (NERF_RGB.expand(len(x), 3), torch.zeros(len(x)))  # noqa: E731
    out = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, empty, through_mesh=True)
    torch.testing.assert_close(out.rgb, BG.expand(3, 3))  # no density: the background, not the mesh
    assert (out.nerf_mask == 0).all()


def test_exterior_in_front_of_the_mesh_is_rendered():
    out, _ = render([0.0], sigma=1e4)  # an opaque shell in front of the body
    assert out.hit.all()
    assert float(out.nerf_mask[0]) > 0.99
    torch.testing.assert_close(out.rgb, NERF_RGB[None], atol=1e-2, rtol=0)


def test_a_ray_grazing_past_the_body_sees_the_exterior_only_near_it():
    out, calls = render([0.35], sigma=30.0)  # misses the sphere, passes 5 cm from it
    assert not out.hit.any() and out.samples_evaluated > 0
    assert 0 < float(out.nerf_mask[0]) < 1
    expected = out.nerf_mask[0] * NERF_RGB + (1 - out.nerf_mask[0]) * BG  # the rest ends on the background
    torch.testing.assert_close(out.rgb[0], expected, atol=1e-5, rtol=0)


def test_silhouette_value_is_the_exact_coverage_and_its_gradient_the_soft_one():
    """Pixel centres 0.3 px inside and outside the sphere's projected edge (radius 30 px in the uv
    frame): the value is the hit, not the soft union (which is above 0.5 just outside the edge);
    the gradient still moves the vertices."""
    mesh = sphere_avatar()
    v = mesh.vertices.clone().requires_grad_(True)
    uv = v[:, :2] * 100
    mesh = PosedMesh(v, mesh.faces, mesh.albedo, uv, mesh.skinning)
    o, d = rays([0.297, 0.303])
    soft_st = RenderSettings(samples=8, perturb=False, sil_hard_value=False, sil_sigma=0.5)
    hard_st = RenderSettings(samples=8, perturb=False, sil_sigma=0.5)
    soft = render_rays(mesh, o, d, o[:, :2] * 100, BG, soft_st).silhouette
    out = render_rays(mesh, o, d, o[:, :2] * 100, BG, hard_st)
    assert out.hit.tolist() == [True, False]
    assert out.silhouette.tolist() == [1.0, 0.0]
    assert soft[1] > 0.5  # the soft union reaches past the edge: why its value is not used
    out.silhouette[1].backward()  # the outside pixel's coverage grows as the rim moves out (+x)
    grad = v.grad
    assert grad.abs().sum() > 0 and torch.isfinite(grad).all()
    rim = (v.detach()[:, 0] > 0.25) & (v.detach()[:, 2].abs() < 0.1)
    assert (grad[rim, 0] >= 0).all() and (grad[rim, 0] > 0).any()


class TwoLayers(torch.nn.Module):
    """Analytic clothing and hair: the clothing a shell below y = 0.05, red; the hair above y = -0.05,
    green (they overlap in a 10-cm band), each of density ``sigma`` within 0.08 m outside the sphere."""

    names = ("clothing", "hair")

    def __init__(self, sigma: float):
        super().__init__()
        self.sigma = sigma

    def with_layers(self, x, carriers=None):  # the carriers bar nothing here
        r, y = x.norm(dim=-1), x[:, 1]
        shell = ((r > 0.3) & (r < 0.38)).float() * self.sigma
        sig = torch.stack([shell * (y < 0.05), shell * (y > -0.05)], -1)
        colours = torch.tensor([[0.9, 0.1, 0.1], [0.1, 0.8, 0.2]])
        share = sig / sig.sum(-1, keepdim=True).clamp_min(1e-30)
        return share @ colours, sig.sum(-1), sig

    def forward(self, x):
        return self.with_layers(x)[:2]


def test_layers_render_as_one_medium_and_each_layer_gets_its_share_of_the_opacity():
    """Rays through the clothing only, the hair only and the band where both are: the composite is the
    render of one NeRF of summed density and density-weighted colour (a plain callable, no layers),
    each layer's opacity is what rendering that layer alone gives where the other is absent, and the
    layers' opacities add up to the exterior's."""
    mesh = sphere_avatar()
    layered = TwoLayers(40.0)
    o = torch.tensor([[0.0, -0.33, 2.0], [0.0, 0.33, 2.0], [0.0, 0.0, 2.0], [0.25, 0.05, 2.0]])
    d = torch.tensor([[0.0, 0.0, -1.0]] * len(o))
    st = RenderSettings(samples=64, box_margin=0.3, max_dist=0.1, perturb=False)
    out = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, layered)
    plain = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, lambda x: layered(x))
    assert plain.layer_masks is None and out.layer_masks.shape == (4, 2)
    torch.testing.assert_close(out.rgb, plain.rgb)
    torch.testing.assert_close(out.nerf_mask, plain.nerf_mask)
    torch.testing.assert_close(out.layer_masks.sum(1), out.nerf_mask)
    assert float(out.nerf_mask.min()) > 0.5  # every ray crosses the shell
    clothing, hair = out.layer_masks.unbind(1)
    torch.testing.assert_close(clothing[0], out.nerf_mask[0])
    torch.testing.assert_close(hair[1], out.nerf_mask[1])
    assert float(hair[0]) == 0.0 and float(clothing[1]) == 0.0
    # in the overlap band each layer has half the density: half the opacity each
    torch.testing.assert_close(clothing[2], hair[2])


def test_layer_shares_are_each_samples_and_its_weights_the_composites():
    """Each sample's log shares: log 1/2 each in the band where the layers overlap with equal density, 0
    for the one layer elsewhere (the other's far below), 0 both where a sample has no density; the sample
    weights are the composite's, summing to the NeRF mask and not differentiated."""
    mesh = sphere_avatar()
    o = torch.tensor([[0.0, -0.33, 2.0], [0.0, 0.0, 2.0]])
    d = torch.tensor([[0.0, 0.0, -1.0]] * len(o))
    st = RenderSettings(samples=64, box_margin=0.3, max_dist=0.1, perturb=False)
    out = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, TwoLayers(40.0))
    assert out.layer_log_shares.shape == (2, out.sample_weights.shape[1], 2)
    torch.testing.assert_close(out.sample_weights.sum(1), out.nerf_mask)
    assert not out.sample_weights.requires_grad
    dense = out.sample_weights > 0
    clothing, hair = out.layer_log_shares.unbind(-1)
    assert bool(dense[0].any()) and bool(dense[1].any())
    assert float(clothing[0][dense[0]].abs().max()) < 1e-6 and float(hair[0][dense[0]].max()) < -80
    half = torch.full_like(clothing[1][dense[1]], math.log(0.5))
    torch.testing.assert_close(clothing[1][dense[1]], half)
    torch.testing.assert_close(hair[1][dense[1]], half)
    assert float(out.layer_log_shares[~dense].abs().max()) == 0.0


def test_a_layer_is_seen_where_its_opacity_gathers():
    """A ray through the clothing shell alone (σ = 40, missing the body) sees the clothing at the opacity's
    weighted mean depth, t_in + 1/σ for a chord of optical depth 15 (analytic, to e^-15); the hair, absent
    on it, at the far bound."""
    mesh = sphere_avatar()
    o, d = torch.tensor([[0.0, -0.33, 2.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    st = RenderSettings(samples=256, box_margin=0.3, max_dist=0.1, perturb=False)
    out = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, TwoLayers(40.0))
    t_in = 2.0 - (0.38**2 - 0.33**2) ** 0.5
    assert float(out.layer_masks[0, 0]) > 0.99 and float(out.layer_masks[0, 1]) == 0.0
    assert abs(float(out.layer_depths[0, 0]) - (t_in + 1 / 40.0)) < 0.004
    assert float(out.layer_depths[0, 1]) > 2.0  # past the shell: the far bound


def test_empty_layers_give_zero_opacity_and_finite_gradients():
    mesh = sphere_avatar()
    o = torch.tensor([[0.0, -0.33, 2.0], [0.0, 0.0, 2.0]])
    d = torch.tensor([[0.0, 0.0, -1.0]] * len(o))
    st = RenderSettings(samples=16, box_margin=0.3, max_dist=0.1, perturb=False)
    scale = torch.tensor(0.0, requires_grad=True)
    layers = TwoLayers(1.0)
    inner = layers.with_layers
    layers.with_layers = lambda x, carriers=None: tuple(
        v * scale if k else v for k, v in enumerate(inner(x, carriers))
    )  # σ → 0·σ
    out = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, layers)
    assert bool((out.layer_masks == 0).all()) and bool((out.nerf_mask == 0).all())
    (out.layer_masks.sum() + out.rgb.sum()).backward()
    assert bool(torch.isfinite(scale.grad))


def _march(offsets, sigma, march, monkeypatch, grad):
    """Rays through the shell of density ``sigma`` with 48 samples, marching ``march`` at a time
    when ``grad`` is off (with gradients a ray takes all its samples at once)."""
    from delta.render import hybrid

    monkeypatch.setattr(hybrid, "MARCH", march)
    mesh = sphere_avatar()
    nerf, calls = shell_nerf(0.3, 0.05, sigma)
    o, d = rays(offsets)
    st = RenderSettings(samples=48, box_margin=0.3, max_dist=0.1, perturb=False)
    with torch.set_grad_enabled(grad):
        return render_rays(mesh, o, d, o[:, :2] * 100, BG, st, nerf), calls


OFFSETS = [0.0, 0.15, 0.28, 0.32, 0.38]  # through the body's middle, its rim, past it in the shell


def test_rays_that_stay_translucent_render_exactly_as_in_one_pass(monkeypatch):
    whole, _ = _march(OFFSETS, 0.5, 4, monkeypatch, grad=True)
    marched, calls = _march(OFFSETS, 0.5, 4, monkeypatch, grad=False)
    assert float(whole.nerf_mask.max()) < 0.5 and len(calls) > 1  # several steps, none opaque
    assert marched.samples_evaluated == whole.samples_evaluated > 0
    assert torch.equal(marched.rgb, whole.rgb) and torch.equal(marched.nerf_mask, whole.nerf_mask)


def test_opaque_rays_stop_early_and_their_colour_moves_by_less_than_the_transmittance_left(monkeypatch):
    from delta.render.hybrid import OPAQUE

    whole, _ = _march(OFFSETS, 400.0, 4, monkeypatch, grad=True)
    marched, _ = _march(OFFSETS, 400.0, 4, monkeypatch, grad=False)
    assert float(whole.nerf_mask.max()) > 1 - 1e-6  # some rays saturate in the shell
    assert 0 < marched.samples_evaluated < whole.samples_evaluated
    assert float((marched.rgb - whole.rgb).abs().max()) <= OPAQUE
    assert float((marched.nerf_mask - whole.nerf_mask).abs().max()) <= OPAQUE
    for march in (1, 7, 47, 100):  # a step of one sample, uneven steps, one step for all
        other, _ = _march(OFFSETS, 400.0, march, monkeypatch, grad=False)
        torch.testing.assert_close(other.rgb, marched.rgb, atol=OPAQUE, rtol=0)


def test_a_mirrored_exterior_is_read_at_its_mirror_image():
    """An exterior only before the sphere (z > 0): seen from behind, the ray meets the body; with every point
    read at its mirror through z = 0, it meets the front's exterior on the back."""
    from delta.geometry.mirror import MirrorGrid

    mesh = sphere_avatar()

    def front_only(x):
        r = x.norm(dim=-1)
        dens = torch.where((r > 0.3) & (x[:, 2] > 0), torch.full_like(r, 1e4), torch.zeros_like(r))
        return NERF_RGB.expand(len(x), 3), dens

    o, d = torch.tensor([[0.0, 0.0, -2.0]]), torch.tensor([[0.0, 0.0, 1.0]])
    st = RenderSettings(samples=32, box_margin=0.3, max_dist=0.1, perturb=False)
    plain = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, front_only)
    torch.testing.assert_close(plain.rgb, MESH_RGB[None], atol=1e-3, rtol=0)
    mirror = MirrorGrid(torch.full((3,), -1.0), 0.5, torch.zeros(4, 4, 4))  # every cell: z -> -z
    seen = render_rays(dataclasses.replace(mesh, mirror=mirror), o, d, o[:, :2] * 100, BG, st, front_only)
    assert float(seen.nerf_mask[0]) > 0.99
    torch.testing.assert_close(seen.rgb, NERF_RGB[None], atol=1e-2, rtol=0)


def band_nerf(near, far, sigma, scale=None):
    """Density ``sigma`` (times ``scale``, a parameter to differentiate) between ``near`` and ``far`` m outside
    the unit test's 0.3-m sphere, none elsewhere."""

    def nerf(x):
        r = x.norm(dim=-1) - 0.3
        dens = torch.where((r > near) & (r < far), torch.full_like(r, sigma), torch.zeros_like(r))
        return NERF_RGB.expand(len(x), 3), dens * (1.0 if scale is None else scale)

    return nerf


def test_the_soft_shell_charges_only_density_farther_from_the_body_than_it():
    """Exterior density within ``render.shell`` of the body costs nothing; beyond it, it does, and the cost
    reaches the density (its gradient, where the ray's colour would not)."""
    mesh = sphere_avatar()
    o, d = rays([0.0, 0.1, 0.2])  # hit the sphere: their exterior lies in front of the body
    st = RenderSettings(samples=32, box_margin=0.3, max_dist=0.1, perturb=False, shell=0.03)
    near = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, band_nerf(0.0, 0.015, 40.0))
    assert (near.optical_depth > 0.1).all()  # a band the rays cross...
    assert (near.shell_depth == 0).all()  # ...inside the shell (vertex distances: within 2 cm of the surface)
    scale = torch.tensor(1.0, requires_grad=True)
    far = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, band_nerf(0.06, 0.09, 40.0, scale))
    assert (far.shell_depth > 0).all() and (far.shell_depth < far.optical_depth).all()  # the ramp is below 1
    far.shell_depth.sum().backward()
    torch.testing.assert_close(scale.grad, far.shell_depth.sum().detach())  # linear in the density
    off = render_rays(mesh, o, d, o[:, :2] * 100, BG, dataclasses.replace(st, shell=0.0), band_nerf(0.06, 0.09, 40.0))
    assert off.shell_depth is None


def test_the_soft_shell_weighs_each_sample_s_optical_depth(monkeypatch):
    """With the ramp at 1 everywhere the shell's depth is the ray's whole optical depth, sample by sample."""
    import delta.render.hybrid as hybrid

    monkeypatch.setattr(hybrid, "shell_ramp", lambda dist, start, room: torch.ones_like(dist))
    mesh = sphere_avatar()
    o, d = rays([0.0, 0.2, 0.35])
    st = RenderSettings(samples=24, box_margin=0.3, max_dist=0.1, perturb=False, shell=0.01)
    out = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, band_nerf(0.0, 0.08, 25.0))
    assert (out.optical_depth > 0).all()
    torch.testing.assert_close(out.shell_depth, out.optical_depth)
