"""The fit's silhouette pieces and joint limits against hand-computed values."""

import numpy as np
import torch

from delta.body.upsample import upsample_body_model
from delta.fitting import silhouette as sil
from delta.fitting import terms
from delta.fitting.limits import joint_limits
from tests.conftest import tree_model


def test_joint_limit_prior_hand_computed():
    lo, hi = torch.tensor([[-1.0, 0.0, 0.0]]), torch.tensor([[1.0, 2.0, 0.0]])
    pose = torch.tensor([[[0.5, 1.0, 0.0]], [[-1.5, 3.0, 0.25]]])
    # frame 0 inside the box; frame 1: 0.5 below, 1.0 above, 0.25 above
    torch.testing.assert_close(terms.joint_limit_prior(pose, lo, hi), torch.tensor([0.0, 0.25 + 1.0 + 0.0625]))


def test_base_faces_come_back_from_an_upsampled_model():
    base = tree_model()
    fine = upsample_body_model(base, 1)
    vids, faces = sil.base_mesh(fine)
    assert vids.tolist() == sorted(set(base.faces.flatten().tolist()))
    assert sorted(map(tuple, np.sort(faces, 1).tolist())) == sorted(map(tuple, np.sort(base.faces.numpy(), 1).tolist()))
    coarse = sil.coarse_mesh(fine, cell=0.0)  # no clustering: the base mesh, reindexed
    torch.testing.assert_close(
        fine.v_template[coarse.vertex_ids][coarse.faces], fine.v_template[torch.from_numpy(faces)]
    )


def test_coarse_mesh_clusters_vertices_of_the_model(body):
    model, _ = body
    coarse = sil.coarse_mesh(model, cell=0.05)
    base_ids, base_faces = sil.base_mesh(model)
    assert 100 < len(coarse.vertex_ids) < len(base_ids) and np.isin(coarse.vertex_ids.numpy(), base_ids).all()
    assert coarse.faces.min() >= 0 and coarse.faces.max() < len(coarse.vertex_ids)
    # every base vertex lies within a cell diagonal of a kept vertex
    kept = model.v_template[coarse.vertex_ids].double()
    d = torch.cdist(model.v_template[torch.from_numpy(base_ids)].double(), kept).amin(1)
    assert d.max() < 0.05 * 3**0.5 * 2


def test_frames_silhouette_hard_squares_per_frame():
    # frame 0: a square over the left half of a 40 x 40 image; frame 1: the right half (at 8 x 8)
    square = lambda u0: torch.tensor([[u0, 0.0], [u0 + 20, 0.0], [u0 + 20, 40.0], [u0, 40.0]], dtype=torch.float64)  # noqa: E731
    uv = torch.stack([square(0.0), square(20.0)])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    out = sil.frames_silhouette(uv, faces, 8, (40, 40), sigma=1e-4)
    expect = torch.zeros(2, 8, 8, dtype=torch.float64)
    expect[0, :, :4], expect[1, :, 4:] = 1.0, 1.0
    torch.testing.assert_close(out, expect, atol=1e-6, rtol=0)
    # term and IoU: frame 0's mask is the full image -> half uncovered; frame 1's mask is exact
    masks = torch.stack([torch.ones(8, 8), expect[1]]).double()
    torch.testing.assert_close(
        sil.silhouette_term(out, masks, fill=0.5), torch.tensor([0.25, 0.0], dtype=torch.float64), atol=1e-6, rtol=0
    )
    torch.testing.assert_close(
        sil.soft_iou(out, masks), torch.tensor([0.5, 1.0], dtype=torch.float64), atol=1e-6, rtol=0
    )


def test_triangles_off_the_image_change_nothing_and_cost_nothing():
    """A body mostly below the image (a head-and-shoulders capture): thousands of triangles whose boxes miss
    the grid leave the silhouette as the visible triangles alone give it, and are never searched."""
    square = torch.tensor([[[8.0, 8.0], [32.0, 8.0], [32.0, 32.0], [8.0, 32.0]]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    visible = sil.frames_silhouette(square, faces, 8, (40, 40), sigma=1e-2)
    n = 20000  # tiny triangles far below the image, clamped onto the strip's bottom edge
    below = torch.stack([torch.rand(n) * 40, 400 + torch.rand(n) * 1000], -1).double()
    uv = torch.cat([square[0], below, below + 0.1, below + torch.tensor([0.0, 0.1]).double()])[None]
    extra = 4 + torch.arange(n)
    more = torch.cat([faces, torch.stack([extra, extra + n, extra + 2 * n], 1)])
    torch.testing.assert_close(sil.frames_silhouette(uv, more, 8, (40, 40), sigma=1e-2), visible, atol=0, rtol=0)
    calls = []
    original = sil.soft_silhouette
    try:
        sil.soft_silhouette = lambda uv, faces, *a, **k: calls.append(len(faces)) or original(uv, faces, *a, **k)
        sil.frames_silhouette(uv, more, 8, (40, 40), sigma=1e-2)
    finally:
        sil.soft_silhouette = original
    assert calls == [2]


def test_supersampled_silhouette_is_the_covered_area():
    # a bar 3 px wide (u in [16, 19]) inside pixel column 3 (u in [15, 20]) of an 8 x 8 grid over 40 x 40:
    # it covers 0.6 of those pixels; one point a pixel (the centre, 17.5) says 1, 4 x 4 points say 0.5
    uv = torch.tensor([[[16.0, 0.0], [19.0, 0.0], [19.0, 40.0], [16.0, 40.0]]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    one = sil.frames_silhouette(uv, faces, 8, (40, 40), sigma=1e-4)
    four = sil.frames_silhouette(uv, faces, 8, (40, 40), sigma=1e-4, supersample=4)
    expect = torch.zeros(1, 8, 8, dtype=torch.float64)
    expect[..., 3] = 1.0
    torch.testing.assert_close(one, expect, atol=1e-4, rtol=0)
    torch.testing.assert_close(four, 0.5 * expect, atol=0.02, rtol=0)  # a point near the shared diagonal: 0.49
    masks = expect.clone()  # the masks narrow the evaluated box; the values stay
    torch.testing.assert_close(sil.frames_silhouette(uv, faces, 8, (40, 40), sigma=1e-4, masks=masks, supersample=4),
                               0.5 * expect, atol=0.02, rtol=0)  # fmt: skip


def test_downsample_masks_area_average():
    m = np.zeros((1, 4, 4), np.uint8)
    m[0, :2, :2] = 255
    torch.testing.assert_close(
        sil.downsample_masks(m, 2), torch.tensor([[[1.0, 0.0], [0.0, 0.0]]], dtype=torch.float64)
    )


def test_the_root_is_not_limited(body):
    model, _ = body
    lo, hi = joint_limits(model)
    assert torch.isinf(lo[0]).all() and torch.isinf(hi[0]).all()
    pose = torch.zeros(1, model.num_joints, 3, dtype=torch.float64)
    pose[0, 0, 1] = 4.65  # a subject turned 266 degrees, written past pi
    assert terms.joint_limit_prior(pose, lo, hi).item() == 0.0


def test_limits_cover_hinges_spine_and_neck_with_the_right_bend_sign(body):
    from delta.fitting.fit import KeypointModel

    model, kp_map = body
    lo, hi = joint_limits(model)
    names = model.joint_names
    for name in ("lowerleg01.L", "lowerarm01.L", "lowerarm01.R", "spine03", "neck01"):
        assert (hi[names.index(name)] - lo[names.index(name)]).max() < 6.0, name
    # an elbow turned about y: inside its range the wrist stays in front; beyond it (hyperextension) it swings back
    kpm, betas = KeypointModel(model, kp_map), torch.zeros(model.num_shape, dtype=torch.float64)
    pose = torch.zeros(3, model.num_joints, 3, dtype=torch.float64)
    for side, wrist in (("L", 7), ("R", 4)):
        j = names.index(f"lowerarm01.{side}")
        inward = -1.0 if side == "L" else 1.0
        pose[1, j, 1], pose[2, j, 1] = inward, -inward
        kp = kpm(betas, pose, torch.zeros(3, 3, dtype=torch.float64))
        assert kp[1, wrist, 2] >= kp[0, wrist, 2] and kp[2, wrist, 2] < kp[0, wrist, 2] - 0.1, side
        prior = terms.joint_limit_prior(pose, lo, hi)
        assert prior[1] == 0 and prior[2] > 0.9, side
        pose.zero_()
    # a knee bent inside its range brings the ankle backwards (-z)
    j = names.index("lowerleg01.L")
    pose[1, j, 0] = 1.0
    kp = kpm(betas, pose, torch.zeros(3, 3, dtype=torch.float64))
    assert kp[1, 13, 2] < kp[0, 13, 2] - 0.1
    assert terms.joint_limit_prior(pose, lo, hi)[1] == 0 and terms.joint_limit_prior(-pose, lo, hi)[1] > 0.9


def test_the_fit_silhouette_stands_outside_the_outline_of_the_body_it_renders(body):
    """The coarse body drawn hard at 256² and area-averaged to the fit's grid is the mask; drawn soft as the fit
    draws it, the excess area over the outline's length is how far the soft outline stands outside. Where
    several triangles lie along the outline, joining them as 1 - prod(1 - p) covers pixels outside it: at the
    fit's softness (0.3 grid px²) about half a grid pixel (4 px of a 512² crop at 64², the margin by which the
    fitted body lies inside a mask: docs/fitting.md), less the sharper it is drawn."""
    from delta.body.lbs import lbs
    from delta.cameras.models import OrthographicCamera
    from delta.fitting.settings import FitConfig

    model, _ = body
    D, F, image = torch.float64, 2, 256
    cfg = FitConfig()
    pose = torch.zeros(F, model.num_joints, 3, dtype=D)
    pose[1, 0, 1] = 1.2
    cam = OrthographicCamera(torch.full((F,), 0.9, dtype=D), torch.tensor([[0.0, 0.05]] * F, dtype=D), image, image)
    coarse = sil.coarse_mesh(model, cfg.sil_cell)
    uv = cam.project(lbs(model, torch.zeros(F, model.num_shape, dtype=D), pose).vertices[:, coarse.vertex_ids])[0]

    def offset(sigma: float) -> torch.Tensor:
        return sil.outline_offset(uv, coarse.faces, image, cfg.sil_size, sigma, cfg.sil_supersample)

    at_fit, sharper, sharpest = offset(cfg.sil_sigma), offset(0.1), offset(0.03)
    assert ((at_fit > 0.35) & (at_fit < 0.8)).all(), at_fit
    assert (sharpest < sharper).all() and (sharper < at_fit).all() and (sharpest.abs() < 0.2).all(), (sharper, sharpest)
