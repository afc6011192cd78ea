"""SMPL-X loading from generated fixtures with the official key names and shapes."""

import os
import pickle

import numpy as np
import pytest
import scipy.sparse
import torch

from delta import DeltaError
from delta.body.lbs import lbs
from delta.body.model import REGION, load_body_model
from delta.body.smplx_loader import SMPLX_JOINT_NAMES, load_smplx
from delta.safe_pickle import load_pickle
from tests.conftest import SMPLX_PARENTS, make_smplx_arrays


@pytest.fixture(scope="module")
def smplx_arrays():
    return make_smplx_arrays()


@pytest.fixture(scope="module")
def smplx_npz(tmp_path_factory, smplx_arrays):
    path = tmp_path_factory.mktemp("smplx") / "SMPLX_NEUTRAL.npz"
    np.savez(path, **smplx_arrays)
    return path


def test_npz_round_trip(smplx_npz, smplx_arrays, tmp_path):
    model = load_smplx(smplx_npz, num_shape=10, num_expression=10)
    a = smplx_arrays
    assert model.num_vertices == 10475 and model.num_joints == 55 and model.num_shape == 10
    assert model.num_expression == 10
    assert model.joint_names == list(SMPLX_JOINT_NAMES)
    assert model.parents.tolist() == SMPLX_PARENTS
    np.testing.assert_allclose(model.shapedirs.numpy(), a["shapedirs"][..., :10])
    np.testing.assert_allclose(model.exprdirs.numpy(), a["shapedirs"][..., 300:310])  # SMPL-X 1.1 layout
    np.testing.assert_allclose(model.joints_template.numpy(), a["J_regressor"] @ a["v_template"])
    # joints follow J_regressor applied to the shaped mesh
    betas = torch.randn(2, 10, dtype=torch.float64)
    out = lbs(model, betas, torch.zeros(2, 55, 3, dtype=torch.float64))
    reg = torch.from_numpy(a["J_regressor"])
    torch.testing.assert_close(out.rest_joints, torch.einsum("jv,bvk->bjk", reg, out.rest_vertices))
    # pose correctives act: the same pose with and without posedirs differs
    pose = 0.3 * torch.randn(1, 55, 3, dtype=torch.float64)
    with_pc = lbs(model, betas[:1], pose).vertices
    model.posedirs = None
    assert not torch.allclose(with_pc, lbs(model, betas[:1], pose).vertices)
    # canonical da-pose spreads the legs
    assert model.canonical_pose[1, 2] > 0 > model.canonical_pose[2, 2]
    # saved in the project's format and read back
    model.to(dtype=torch.float32).save(tmp_path / "smplx.npz")
    back = load_body_model(tmp_path / "smplx.npz", dtype=torch.float64)
    torch.testing.assert_close(back.v_template, model.v_template, rtol=0, atol=1e-6)


def test_regions_follow_dominant_joints(smplx_npz, smplx_arrays):
    model = load_smplx(smplx_npz)
    dominant = smplx_arrays["weights"].argmax(1)
    head = SMPLX_JOINT_NAMES.index("head")
    wrist = SMPLX_JOINT_NAMES.index("left_wrist")
    assert (model.regions[torch.from_numpy(dominant == head)] == REGION["face"]).all()
    assert (model.regions[torch.from_numpy(dominant == wrist)] == REGION["hands"]).all()
    assert (model.regions[torch.from_numpy(dominant == 0)] == REGION["body"]).all()


def test_pkl_with_sparse_regressor(tmp_path, smplx_arrays):
    data = dict(smplx_arrays)
    data["J_regressor"] = scipy.sparse.csc_matrix(data["J_regressor"])
    data["posedirs"] = data["posedirs"].reshape(-1, 9 * 54).T.copy()  # the (P, V*3) layout
    path = tmp_path / "SMPLX_NEUTRAL.pkl"
    path.write_bytes(pickle.dumps(data, protocol=2))
    model = load_smplx(path)
    ref = load_smplx_from_arrays(tmp_path, smplx_arrays)
    torch.testing.assert_close(model.joints_template, ref.joints_template)
    torch.testing.assert_close(model.posedirs, ref.posedirs)


def load_smplx_from_arrays(tmp_path, arrays):
    path = tmp_path / "ref.npz"
    np.savez(path, **arrays)
    return load_smplx(path)


def test_smaller_legacy_shape_space(tmp_path):
    """SMPL-X 1.0 files hold 10 shape + 10 expression components."""
    arrays = make_smplx_arrays(num_vertices=300, num_components=20)
    path = tmp_path / "SMPLX_NEUTRAL.npz"
    np.savez(path, **arrays)
    model = load_smplx(path, num_shape=10, num_expression=10)
    np.testing.assert_allclose(model.exprdirs.numpy(), arrays["shapedirs"][..., 10:])
    with pytest.raises(DeltaError, match="holds 10 shape and 10 expression"):
        load_smplx(path, num_shape=20)


def test_missing_file_says_where_to_put_it(tmp_path):
    with pytest.raises(DeltaError) as err:
        load_smplx(tmp_path / "nope" / "SMPLX_NEUTRAL.npz")
    msg = str(err.value)
    assert "nope/SMPLX_NEUTRAL.npz" in msg and "body_model.smplx_path" in msg and "anny" in msg


def test_corrupt_file_is_named(tmp_path):
    path = tmp_path / "SMPLX_NEUTRAL.npz"
    path.write_bytes(b"this is not a zip archive")
    with pytest.raises(DeltaError, match="SMPLX_NEUTRAL.npz.*not a readable SMPL-X npz"):
        load_smplx(path)


def test_missing_key_is_named(tmp_path):
    arrays = make_smplx_arrays(num_vertices=200)
    del arrays["weights"]
    path = tmp_path / "SMPLX_NEUTRAL.npz"
    np.savez(path, **arrays)
    with pytest.raises(DeltaError, match=r"missing SMPL-X keys \['weights'\]"):
        load_smplx(path)


def test_wrong_shape_is_named(tmp_path):
    arrays = make_smplx_arrays(num_vertices=200)
    arrays["weights"] = arrays["weights"][:, :50]
    path = tmp_path / "SMPLX_NEUTRAL.npz"
    np.savez(path, **arrays)
    with pytest.raises(DeltaError, match="'weights' has shape"):
        load_smplx(path)


class _Exploit:
    def __reduce__(self):
        return (os.system, ("echo pwned > /tmp/delta_pwned",))


def test_restricted_unpickler_refuses_code(tmp_path):
    path = tmp_path / "SMPLX_NEUTRAL.pkl"
    path.write_bytes(pickle.dumps({"v_template": _Exploit()}))
    with pytest.raises(DeltaError, match="refusing to load 'posix.system'"):
        load_smplx(path)
    assert not os.path.exists("/tmp/delta_pwned")


def test_restricted_unpickler_reads_plain_values(tmp_path):
    value = {"camera_f": np.array([1000.0, 1001.0]), "width": 1080, "name": "cam", "k": [0.1, 0.2]}
    path = tmp_path / "camera.pkl"
    path.write_bytes(pickle.dumps(value, protocol=2))
    back = load_pickle(path)
    np.testing.assert_array_equal(back["camera_f"], value["camera_f"])
    assert back["width"] == 1080 and back["name"] == "cam" and back["k"] == [0.1, 0.2]
