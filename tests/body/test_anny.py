"""The converted Anny model against Anny's own forward pass."""

import dataclasses

import numpy as np
import pytest
import torch

from delta.body.anny_convert import (
    ANNY_TO_SMPLX,
    anny_pose_deltas,
    anny_rest,
    convert_anny,
    merge_map,
    project_shape,
    sample_phenotypes,
)
from delta.body.lbs import batch_rodrigues, lbs
from delta.body.model import REGION, load_body_model, load_metadata

pytestmark = pytest.mark.slow
C = torch.as_tensor(ANNY_TO_SMPLX)


def anny_forward(anny_model, phenotypes, pose, transl, actions=None):
    """Anny's own posed vertices (project axes) for our axis-angle pose (project axes), with
    ``actions`` (B, 52) facial-action activations for a model built with them."""
    rest = anny_rest(anny_model, phenotypes, actions)
    rot = C.T @ batch_rodrigues(pose) @ C
    deltas = anny_pose_deltas(rot, transl @ C, rest["rest_bone_poses"], anny_model.reference_bone_orientations,
                              anny_model.bone_parents)  # fmt: skip
    out = anny_model(pose_parameters=deltas, phenotype_kwargs=phenotypes, facial_actions=actions)
    return out["vertices"] @ C.T, rest


def random_pose(batch, joints, scale, seed):
    gen = torch.Generator().manual_seed(seed)
    return scale * torch.randn(batch, joints, 3, generator=gen, dtype=torch.float64)


def test_pose_mapping_is_exact_for_a_given_shape(anny_model, anny_conversion):
    """With the template set to one phenotype's exact rest shape, LBS equals Anny to round-off."""
    ph = sample_phenotypes(1, 6, seed=77)
    rest = anny_rest(anny_model, ph)
    exact = dataclasses.replace(
        anny_conversion.model,
        v_template=rest["rest_vertices"][0] @ C.T,
        joints_template=rest["rest_bone_heads"][0] @ C.T,
    )
    assert exact.num_joints == len(anny_model.bone_labels)  # nothing merged in this fixture
    pose = random_pose(3, exact.num_joints, 0.6, seed=1)
    transl = torch.tensor([[0.1, -0.2, 0.3]], dtype=torch.float64).expand(3, 3)
    ours = lbs(exact, torch.zeros(3, exact.num_shape, dtype=torch.float64), pose, transl=transl).vertices
    ref, _ = anny_forward(anny_model, ph.expand(3, -1), pose, transl)
    assert (ours - ref).norm(dim=-1).max() < 1e-9


def test_converted_model_reproduces_anny(anny_model, anny_conversion):
    """Random phenotypes within range and random poses: report the max vertex error in mm."""
    ph = sample_phenotypes(8, 6, seed=123)
    pose = random_pose(8, anny_conversion.model.num_joints, 0.5, seed=2)
    transl = torch.zeros(8, 3, dtype=torch.float64)
    ref, rest = anny_forward(anny_model, ph, pose, transl)
    betas = project_shape(anny_conversion, rest["rest_vertices"], rest["rest_bone_heads"])
    ours = lbs(anny_conversion.model, betas, pose).vertices
    err_mm = 1000 * (ours - ref).norm(dim=-1)
    rest_err_mm = 1000 * (lbs(anny_conversion.model, betas, torch.zeros_like(pose)).vertices
                          - rest["rest_vertices"] @ C.T).norm(dim=-1)  # fmt: skip
    print(f"\nAnny vs converted (32 PCA comps, 256 samples): max {err_mm.max():.3f} mm, "
          f"mean {err_mm.mean():.4f} mm; rest-shape max {rest_err_mm.max():.3f} mm")  # fmt: skip
    assert err_mm.max() < 10.0
    assert err_mm.mean() < 1.5
    # the posed error is the shape-space truncation error carried along, not a pose mismatch
    assert err_mm.max() < 1.5 * rest_err_mm.max() + 0.05
    assert anny_conversion.explained_variance.sum() > 0.9999


def test_more_components_reduce_the_error(anny_model):
    ph = sample_phenotypes(4, 6, seed=9)
    rest = anny_rest(anny_model, ph)
    errors = []
    for k in (4, 32):
        conv = convert_anny(num_shape=k, num_samples=128, seed=0, anny_model=anny_model)
        beta = project_shape(conv, rest["rest_vertices"], rest["rest_bone_heads"])
        v = lbs(conv.model, beta, torch.zeros(4, conv.model.num_joints, 3, dtype=torch.float64)).vertices
        errors.append((v - rest["rest_vertices"] @ C.T).norm(dim=-1).max().item())
    assert errors[1] < errors[0]


def test_merged_bones_match_full_model_when_unposed(anny_model, anny_conversion):
    merged = convert_anny(num_shape=32, num_samples=256, seed=0, merge_bones=["fingers", "toes"],
                          anny_model=anny_model).model  # fmt: skip
    full = anny_conversion.model
    assert merged.num_joints < full.num_joints
    assert not any(n.startswith(("finger", "toe", "metacarpal")) for n in merged.joint_names)
    kept = [full.joint_names.index(n) for n in merged.joint_names]
    pose = random_pose(2, full.num_joints, 0.4, seed=5)
    betas = torch.randn(2, 32, dtype=torch.float64)
    pose_full = torch.zeros_like(pose)
    pose_full[:, kept] = pose[:, kept]
    a = lbs(full, betas, pose_full).vertices
    b = lbs(merged, betas, pose[:, kept]).vertices
    assert (a - b).abs().max() < 1e-9


def test_merge_map_unknown_group_is_named():
    with pytest.raises(Exception, match="unknown group.*'wings'"):
        merge_map(["root"], [-1], ["wings"])


def test_axes_and_regions(anny_conversion):
    m = anny_conversion.model
    v = m.v_template
    height = v[:, 1].max() - v[:, 1].min()
    assert 1.4 < height < 2.0  # y is up, metres
    face = v[m.regions == REGION["face"]]
    hands = v[m.regions == REGION["hands"]]
    feet = v[m.regions == REGION["feet"]]
    assert face[:, 1].mean() > v[:, 1].max() - 0.35  # the head is at the top
    assert feet[:, 1].mean() < v[:, 1].min() + 0.15
    assert hands[:, 0].abs().mean() > 0.4  # hands hang at the ends of the A-pose arms
    nose_z = face[:, 2].max()
    assert nose_z > v[:, 2].mean()  # the face looks towards +z
    for name in ("body", "face", "hands", "feet"):
        assert (m.regions == REGION[name]).sum() > 100


def test_saved_model_round_trip(tmp_path, anny_conversion):
    path = tmp_path / "anny.npz"
    anny_conversion.model.save(path, explained_variance=anny_conversion.explained_variance)
    loaded = load_body_model(path, dtype=torch.float64)
    for field in ("v_template", "shapedirs", "weights", "joints_template"):
        torch.testing.assert_close(getattr(loaded, field), getattr(anny_conversion.model, field))
    assert loaded.joint_names == anny_conversion.model.joint_names
    with np.load(path, allow_pickle=False) as data:  # no pickled objects inside
        assert "meta_explained_variance" in data.files
    np.testing.assert_allclose(load_metadata(path)["explained_variance"], anny_conversion.explained_variance)


@pytest.mark.parametrize("sign", [-5.0, 5.0])
def test_extreme_shapes_and_poses_on_anny(anny_conversion, sign):
    """Shape at ±5 standard deviations, joint angles beyond π, a batch of 256: finite values and gradients."""
    m = anny_conversion.model.to(dtype=torch.float32)
    gen = torch.Generator().manual_seed(int(sign))
    betas = torch.full((256, m.num_shape), sign).requires_grad_()
    pose = (4.0 * torch.randn(256, m.num_joints, 3, generator=gen)).requires_grad_()
    out = lbs(m, betas, pose)
    assert torch.isfinite(out.vertices).all() and torch.isfinite(out.vertex_transforms).all()
    out.vertices.square().mean().backward()
    assert torch.isfinite(betas.grad).all() and torch.isfinite(pose.grad).all()
    # every coefficient at ±5σ at once extrapolates far (|β| = 5·sqrt(32) σ), yet stays metres, not an explosion
    height = out.rest_vertices[0, :, 1].max() - out.rest_vertices[0, :, 1].min()
    assert 0.3 < height < 5.0
