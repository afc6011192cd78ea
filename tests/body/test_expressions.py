"""Anny's facial actions as the body model's expression space, against Anny's own forward pass."""

import dataclasses

import numpy as np
import pytest
import torch

from delta import DeltaError
from delta.body.anny_convert import anny_rest, sample_phenotypes
from delta.body.expressions import ExpressionSpace, anny_expression_space, with_expressions
from delta.body.lbs import lbs
from delta.body.model import REGION, load_body_model
from delta.body.upsample import upsample_body_model
from tests.body.test_anny import C, anny_forward, random_pose

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def space(anny_face_model):
    return anny_expression_space(anny_face_model)


@pytest.fixture(scope="module")
def face_model(anny_conversion, space):
    return with_expressions(anny_conversion.model, space)


def activations(batch, num, seed):
    return torch.rand(batch, num, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def posed(model, pose, acts=None):
    betas = torch.zeros(pose.shape[0], model.num_shape, dtype=torch.float64)
    return lbs(model, betas, pose, expression=acts).vertices


def test_arkit_names_and_sparsity(space):
    assert space.num_expression == 52
    assert {"jawOpen", "eyeBlinkLeft", "mouthSmileRight", "tongueOut"} <= set(space.names)
    assert 0 < len(space.vertex_ids) < space.num_vertices / 3


def test_posed_expressions_match_anny(anny_face_model, anny_conversion, space):
    """With the template set to one phenotype's rest shape, posed vertices with random activations
    equal Anny's forward pass with the same facial actions to round-off."""
    ph = sample_phenotypes(1, 6, seed=31).expand(3, -1)
    rest = anny_rest(anny_face_model, ph[:1])
    exact = dataclasses.replace(anny_conversion.model, v_template=rest["rest_vertices"][0] @ C.T,
                                joints_template=rest["rest_bone_heads"][0] @ C.T)  # fmt: skip
    exact = with_expressions(exact, space)
    pose = random_pose(3, exact.num_joints, 0.4, seed=5)
    acts = activations(3, space.num_expression, seed=6)
    transl = torch.zeros(3, 3, dtype=torch.float64)
    ref, rest_acted = anny_forward(anny_face_model, ph, pose, transl, acts)
    neutral, _ = anny_forward(anny_face_model, ph, pose, transl)
    # the facial actions move no bone (to round-off), which is why expressions need no joints_exprdirs
    assert (rest_acted["rest_bone_heads"] - rest["rest_bone_heads"]).abs().max() < 1e-12
    assert (posed(exact, pose, acts) - ref).norm(dim=-1).max() < 1e-9
    assert (ref - neutral).norm(dim=-1).max() > 5e-3  # the faces did change


def test_zero_is_neutral_and_activations_are_linear(face_model):
    pose = random_pose(1, face_model.num_joints, 0.3, seed=8)
    E = face_model.num_expression
    a, b = activations(1, E, seed=1), activations(1, E, seed=2)
    neutral = posed(face_model, pose)
    assert torch.equal(posed(face_model, pose, torch.zeros(1, E, dtype=torch.float64)), neutral)
    da, db = posed(face_model, pose, a) - neutral, posed(face_model, pose, b) - neutral
    dab = posed(face_model, pose, a + b) - neutral
    assert (dab - da - db).abs().max() < 1e-12
    assert (posed(face_model, pose, 2.5 * a) - neutral - 2.5 * da).abs().max() < 1e-12
    # a prefix of the coefficients drives the first actions only
    first = posed(face_model, pose, a[:, :5]) - neutral
    assert (
        first - (posed(face_model, pose, torch.cat([a[:, :5], torch.zeros(1, E - 5)], 1)) - neutral)
    ).abs().max() < 1e-12


def test_actions_move_the_face_only(face_model, space):
    moved = np.linalg.norm(space.dirs, axis=1).max(1)  # (K,) largest displacement per touched vertex
    regions = face_model.regions.numpy()[space.vertex_ids]
    inside = np.isin(regions, [REGION["face"], REGION["eyes"], REGION["mouth"]])
    assert moved[inside].max() > 0.03  # jawOpen drops the chin by centimetres
    assert moved[~inside].max() < 2e-3  # the neck seam follows by a millimetre at most
    assert not np.isin(regions, [REGION["hands"], REGION["feet"]]).any()


def test_upsampled_model_interpolates_the_base_actions(anny_conversion, space):
    base = with_expressions(anny_conversion.model, space)
    sub = with_expressions(upsample_body_model(anny_conversion.model, 1), space)
    acts = activations(1, space.num_expression, seed=3)
    zero = torch.zeros(1, base.num_joints, 3, dtype=torch.float64)
    d_base = (posed(base, zero, acts) - posed(base, zero))[0]
    d_sub = (posed(sub, zero, acts) - posed(sub, zero))[0]
    expect = (d_base[sub.embed_vertex_ids] * sub.embed_bary[..., None]).sum(1)
    assert (d_sub - expect).abs().max() < 1e-12
    assert torch.equal(d_sub[: base.num_vertices], d_base)  # subdivision keeps the base vertices first


def test_files_round_trip_and_bad_files(tmp_path, face_model, space):
    space.save(tmp_path / "expr.npz")
    again = ExpressionSpace.load(tmp_path / "expr.npz")
    assert again.names == space.names and np.array_equal(again.vertex_ids, space.vertex_ids)
    assert np.abs(again.dirs - space.dirs).max() < 1e-7  # stored as float32
    face_model.save(tmp_path / "model.npz")
    loaded = load_body_model(tmp_path / "model.npz", dtype=torch.float64)
    assert loaded.expression_names == space.names and loaded.num_expression == 52
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DeltaError, match="junk.npz: not an expression-space file"):
        ExpressionSpace.load(tmp_path / "junk.npz")
    bad = dataclasses.replace(space, vertex_ids=space.vertex_ids + space.num_vertices)
    with pytest.raises(DeltaError, match="'vertex_ids' index outside"):
        bad.validate("bad")
    small = dataclasses.replace(face_model, v_template=face_model.v_template[:10], embed_vertex_ids=None)
    with pytest.raises(DeltaError, match=f"holds {space.num_vertices} vertices"):
        with_expressions(small, space)
    with pytest.raises(DeltaError, match="'expression_names' has 2 names for 52"):
        dataclasses.replace(face_model, expression_names=["a", "b"]).validate("named")


def test_a_model_without_facial_actions_is_refused(anny_model):
    with pytest.raises(DeltaError, match="built without facial actions"):
        anny_expression_space(anny_model)


def test_an_open_jaw_shows_the_inner_mouth_not_the_inside_of_the_head(face_model):
    """Anny's mesh is closed through the mouth (its mouth cavity and tongue, region ``mouth``), which is
    what the paper adds to FLAME as inner-mouth faces. Rays from the front down the face's midline: with
    the jaw open those between the lips stop on mouth faces a few centimetres behind the lips (not on the
    back of the head's inside, ~20 cm further); closed, the same rays stop on the lips' skin."""
    from delta.geometry.raymesh import ray_mesh_hits

    jaw = face_model.expression_names.index("jawOpen")
    pose = face_model.canonical_pose[None].to(torch.float64)
    shut = posed(face_model, pose, torch.zeros(1, face_model.num_expression, dtype=torch.float64))[0]
    acts = torch.zeros(1, face_model.num_expression, dtype=torch.float64)
    acts[0, jaw] = 1.0
    open_ = posed(face_model, pose, acts)[0]
    moved = (open_ - shut).norm(dim=-1) > 3e-3  # the jaw, chin and lips
    lo, hi = shut[moved].amin(0), shut[moved].amax(0)
    ys = torch.linspace(float(lo[1]), float(hi[1]), 80, dtype=torch.float64)
    start = float(hi[2]) + 0.3
    origins = torch.stack([torch.full_like(ys, float(lo[0] + hi[0]) / 2), ys, torch.full_like(ys, start)], -1)
    dirs = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand_as(origins)
    regions = face_model.regions.to(torch.long)
    hit = {}
    for name, verts in (("open", open_), ("shut", shut)):
        h = ray_mesh_hits(verts, face_model.faces, origins, dirs)
        assert bool(h.hit.all()), name
        hit[name] = (start - h.t, regions[face_model.faces[h.face, 0]])
    z_open, region_open = hit["open"]
    z_shut, region_shut = hit["shut"]
    gap = z_open < z_shut - 0.02  # rays that now pass between the lips
    assert int(gap.sum()) >= 5
    assert bool((region_open[gap] == REGION["mouth"]).all())
    behind_lips = z_shut[gap] - z_open[gap]
    assert float(behind_lips.max()) < 0.08, behind_lips
    assert bool((region_shut[gap] != REGION["mouth"]).all())  # closed, the lips cover it
