"""Motion files and their retargeting: the readers' checks, SMPL-family poses onto Anny's skeleton
against an independent forward kinematics of SMPL's T-pose bones, and the rigid placement."""

import math

import numpy as np
import pytest
import torch
from kornia.geometry.conversions import rotation_matrix_to_axis_angle
from scipy.spatial.transform import Rotation

from delta import DeltaError
from delta.applications.animate import onto_floor, place
from delta.applications.motion import Motion, read_motion, resample
from delta.applications.retarget import FAMILY_JOINTS, JOINT_MAP, SMPL_BODY, SMPL_BODY_PARENTS, retarget_smpl_family
from delta.body.lbs import lbs
from delta.body.model import load_body_model
from delta.body.upright import angle_deg, axis_angle_matrix, heading, signed_angle

#: SMPL's T-pose bone directions (start joint -> end joint) the test's own forward kinematics uses
T_BONES = {("left_shoulder", "left_elbow"): (1, 0, 0), ("right_shoulder", "right_elbow"): (-1, 0, 0),
           ("left_elbow", "left_wrist"): (1, 0, 0), ("right_elbow", "right_wrist"): (-1, 0, 0),
           ("left_collar", "left_shoulder"): (1, 0, 0), ("right_collar", "right_shoulder"): (-1, 0, 0),
           ("left_hip", "left_knee"): (0, -1, 0), ("right_hip", "right_knee"): (0, -1, 0),
           ("left_knee", "left_ankle"): (0, -1, 0), ("right_knee", "right_ankle"): (0, -1, 0)}  # fmt: skip
#: the same bones on Anny's skeleton (start joint, end joint)
ANNY_BONES = {("left_shoulder", "left_elbow"): ("upperarm01.L", "lowerarm01.L"),
              ("right_shoulder", "right_elbow"): ("upperarm01.R", "lowerarm01.R"),
              ("left_elbow", "left_wrist"): ("lowerarm01.L", "wrist.L"),
              ("right_elbow", "right_wrist"): ("lowerarm01.R", "wrist.R"),
              ("left_collar", "left_shoulder"): ("clavicle.L", "upperarm01.L"),
              ("right_collar", "right_shoulder"): ("clavicle.R", "upperarm01.R"),
              ("left_hip", "left_knee"): ("upperleg01.L", "lowerleg01.L"),
              ("right_hip", "right_knee"): ("upperleg01.R", "lowerleg01.R"),
              ("left_knee", "left_ankle"): ("lowerleg01.L", "foot.L"),
              ("right_knee", "right_ankle"): ("lowerleg01.R", "foot.R")}  # fmt: skip


@pytest.fixture(scope="module")
def anny(anny_files):
    return load_body_model(anny_files["body"], dtype=torch.float64)


def skeleton(body):
    return body.joint_names, body.parents.numpy(), body.joints_template.numpy()


def source_bone_directions(poses: np.ndarray) -> dict:
    """Posed SMPL bone directions by forward kinematics written here: G_j = G_parent R_j, bone = G_start d_T."""
    out = {}
    for f, pose in enumerate(poses):
        G = []
        for j, p in enumerate(SMPL_BODY_PARENTS):
            R = Rotation.from_rotvec(pose[j])
            G.append(R if p < 0 else G[p] * R)
        for (a, b), d in T_BONES.items():
            out.setdefault((a, b), []).append(G[SMPL_BODY.index(a)].apply(d))
    return {k: np.array(v) for k, v in out.items()}


def anny_bone_directions(body, local: np.ndarray) -> dict:
    """Posed bone directions of Anny's skeleton from the project's LBS joints."""
    joints = lbs(body, torch.zeros(len(local), body.num_shape, dtype=torch.float64),
                 torch.from_numpy(local)).joints.numpy()  # fmt: skip
    names = body.joint_names
    out = {}
    for key, (a, b) in ANNY_BONES.items():
        d = joints[:, names.index(b)] - joints[:, names.index(a)]
        out[key] = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return out


def smplh(frames: np.ndarray) -> np.ndarray:
    """(F, 52, 3) SMPL+H poses with the given (F, 22, 3) body rotations and random hands."""
    hands = np.random.default_rng(0).normal(0, 0.3, size=(len(frames), 30, 3))
    return np.concatenate([frames, hands], 1)


def test_t_pose_and_arms_down_have_known_bone_directions(anny):
    """SMPL's zero pose is a T-pose: Anny's arms come out along ±x, its legs along -y; SMPL's shoulders turned
    ∓90° about z put both upper arms straight down."""
    body = np.zeros((2, 22, 3))
    body[1, SMPL_BODY.index("left_shoulder"), 2] = -np.pi / 2
    body[1, SMPL_BODY.index("right_shoulder"), 2] = np.pi / 2
    local = retarget_smpl_family(smplh(body), "smplh", *skeleton(anny))
    dirs = anny_bone_directions(anny, local)
    for key in (("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist")):
        np.testing.assert_allclose(dirs[key][0], [1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(dirs[("right_shoulder", "right_elbow")][0], [-1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(dirs[("left_hip", "left_knee")][0], [0, -1, 0], atol=1e-9)
    for side in ("left", "right"):
        np.testing.assert_allclose(dirs[(f"{side}_shoulder", f"{side}_elbow")][1], [0, -1, 0], atol=1e-9)


def test_random_poses_point_every_mapped_bone_as_the_source_does(anny):
    """For random SMPL poses (root and spine included), each mapped Anny bone points along the source bone,
    as the test's own forward kinematics of SMPL's T-pose bones has it."""
    rng = np.random.default_rng(3)
    body = rng.normal(0, 0.6, size=(6, 22, 3))
    local = retarget_smpl_family(smplh(body), "smplh", *skeleton(anny))
    want, got = source_bone_directions(body), anny_bone_directions(anny, local)
    for key in T_BONES:
        cos = np.sum(want[key] * got[key], -1)
        assert cos.min() > 1 - 1e-9, (key, cos)


def test_unmapped_joints_stay_at_rest_and_the_families_agree(anny):
    """Joints the map does not name keep their rest orientation; SMPL, SMPL+H and SMPL-X rows of the same body
    pose retarget alike (their extra joints are not used, except SMPL-X's eyes)."""
    rng = np.random.default_rng(4)
    body = rng.normal(0, 0.4, size=(3, 22, 3))
    names = anny.joint_names
    out = {fam: retarget_smpl_family(np.concatenate([body, rng.normal(0, 0.3, size=(3, len(FAMILY_JOINTS[fam]) - 22, 3))], 1),
                                     fam, *skeleton(anny)) for fam in FAMILY_JOINTS}  # fmt: skip
    eyes = [names.index(n) for n in ("eye.L", "eye.R")]
    keep = [j for j in range(len(names)) if j not in eyes]
    np.testing.assert_allclose(out["smpl"][:, keep], out["smplh"][:, keep], atol=1e-9)
    np.testing.assert_allclose(out["smpl"][:, keep], out["smplx"][:, keep], atol=1e-9)
    mapped = set(JOINT_MAP)
    rest = [j for j, n in enumerate(names) if n not in mapped and names[int(anny.parents[j])] not in mapped]
    assert rest and np.abs(out["smplh"][:, rest]).max() < 1e-9
    # a joint right under a mapped one undoes nothing of it: pelvis.L's local rotation is the identity
    assert np.abs(out["smplh"][:, names.index("pelvis.L")]).max() < 1e-9


def test_an_smplx_body_model_takes_the_rotations_as_they_are():
    from delta.body.smplx_loader import SMPLX_JOINT_NAMES

    names = list(SMPLX_JOINT_NAMES)
    poses = np.random.default_rng(5).normal(size=(2, 55, 3))
    out = retarget_smpl_family(poses, "smplx", names, np.zeros(len(names), int), np.zeros((len(names), 3)))
    np.testing.assert_array_equal(out, poses)
    out = retarget_smpl_family(poses[:, :24] * 0 + poses[:, :24], "smpl", names, np.zeros(len(names), int),
                               np.zeros((len(names), 3)))  # fmt: skip
    np.testing.assert_array_equal(out[:, :22], poses[:, :22])
    assert np.all(out[:, 22:] == 0)


# ------------------------------------------------------------------ files
def write(path, **arrays):
    np.savez(path, **arrays)
    return path


def test_the_body_models_own_motion_reads_back(tmp_path, anny):
    names, parents, rest = skeleton(anny)
    J = len(names)
    poses = np.random.default_rng(6).normal(0, 0.2, size=(7, J, 3))
    transl = np.random.default_rng(7).normal(size=(7, 3))
    m = read_motion(write(tmp_path / "own.npz", poses=poses, transl=transl, joint_names=np.array(names), fps=25.0),
                    names, parents, rest)  # fmt: skip
    np.testing.assert_array_equal(m.poses, poses)
    np.testing.assert_array_equal(m.transl, transl)
    assert (m.fps, m.source, m.up) == (25.0, "body model", None)
    flat = read_motion(write(tmp_path / "flat.npz", poses=poses.reshape(7, -1), up=np.array([0.0, -2.0, 0.0])),
                       names, parents, rest)  # fmt: skip
    np.testing.assert_array_equal(flat.poses, poses)
    assert np.all(flat.transl == 0) and flat.fps == 30.0
    np.testing.assert_array_equal(flat.up, [0.0, -1.0, 0.0])  # a fit's capture up, unit length
    for bad, says in (
        (np.zeros(3), "zero vector"),
        (np.ones(2), "three finite numbers"),
        (np.array([0, np.nan, 1]), "finite"),
    ):
        with pytest.raises(DeltaError, match=says):
            read_motion(write(tmp_path / "bad.npz", poses=poses, up=bad), names, parents, rest)


def test_an_amass_archive_is_retargeted(tmp_path, anny):
    names, parents, rest = skeleton(anny)
    body = np.random.default_rng(8).normal(0, 0.3, size=(5, 22, 3))
    trans = np.random.default_rng(9).normal(size=(5, 3))
    m = read_motion(write(tmp_path / "amass.npz", poses=smplh(body).reshape(5, -1), trans=trans,
                          mocap_framerate=np.array(120.0), gender=np.array("female")), names, parents, rest)  # fmt: skip
    assert m.source == "smplh" and m.fps == 120.0 and m.poses.shape == (5, len(names), 3)
    np.testing.assert_array_equal(m.up, [0.0, 0.0, 1.0])  # AMASS's world is z-up
    np.testing.assert_allclose(m.poses, retarget_smpl_family(smplh(body), "smplh", names, parents, rest))
    np.testing.assert_array_equal(m.transl, trans)


@pytest.mark.parametrize(
    "arrays, message",
    [
        ({"poses": np.zeros((0, 156))}, "no frames"),
        ({"poses": np.zeros((4, 50))}, "expected (frames, "),
        ({"trans": np.zeros((4, 3))}, "no 'poses' array"),
        ({"poses": np.zeros((4, 156)), "trans": np.zeros((3, 3))}, "'trans' has shape (3, 3)"),
        ({"poses": np.where(np.arange(4)[:, None] == 2, np.nan, np.zeros((4, 156)))}, "the first frame 2"),
        ({"poses": np.zeros((4, 156)), "mocap_framerate": np.array(0.0)}, "positive frame rate"),
        ({"poses": np.zeros((4, 3, 3)), "joint_names": np.array(["a", "b", "c"])}, "not the body model's"),
        ({"poses": np.array(["x"] * 4)}, "not numbers"),
    ],
)
def test_a_bad_motion_file_gets_one_clear_error(tmp_path, anny, arrays, message):
    path = write(tmp_path / "bad.npz", **arrays)
    with pytest.raises(DeltaError, match=r"bad\.npz") as e:
        read_motion(path, *skeleton(anny))
    assert message in str(e.value)


def test_pickles_and_other_files_are_refused_without_running_them(tmp_path, anny):
    np.savez(tmp_path / "pickled.npz", poses=np.array([{"a": 1}], dtype=object))
    with pytest.raises(DeltaError, match="pickled objects"):
        read_motion(tmp_path / "pickled.npz", *skeleton(anny))
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(DeltaError, match="not a readable npz"):
        read_motion(tmp_path / "text.npz", *skeleton(anny))
    with pytest.raises(DeltaError, match="no such motion file"):
        read_motion(tmp_path / "missing.npz", *skeleton(anny))


def test_resampling_keeps_every_kth_frame_and_caps_the_count():
    m = Motion(np.arange(60)[:, None, None] * np.ones((60, 2, 3)), np.zeros((60, 3)), 60.0, "body model")
    r = resample(m, 12.0, 0)
    np.testing.assert_array_equal(r.poses[:, 0, 0], np.arange(0, 60, 5))
    assert r.fps == 12.0
    assert resample(m, 12.0, 4).num_frames == 4
    slow = resample(Motion(m.poses, m.transl, 10.0, "x"), 12.0, 0)  # never faster than the source
    assert slow.num_frames == 60 and slow.fps == 10.0


# ------------------------------------------------------------------ placement
def test_placement_stands_the_motion_on_the_captures_up_from_the_anchor_and_is_blind_to_its_world():
    """The motion's up becomes the capture's up; its first frame starts at the anchor's place facing the
    anchor's way, keeping its own lean; the same motion recorded in a turned and shifted world (AMASS's
    z-up) places to the same frames; its relative movement is kept."""
    rng = np.random.default_rng(10)
    root = torch.from_numpy(rng.normal(0, 0.7, size=(6, 3)))
    transl = torch.from_numpy(rng.normal(size=(6, 3)))
    motion_up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    up = torch.nn.functional.normalize(torch.tensor([0.1, -0.95, 0.3], dtype=torch.float64), dim=0)
    anchor_root, anchor_t = (
        torch.tensor([2.9, 0.4, -0.2], dtype=torch.float64),
        torch.tensor([0.3, -0.1, 4.0], dtype=torch.float64),
    )
    r, t = place(root, transl, anchor_root, anchor_t, up, motion_up)
    rot = lambda a: Rotation.from_rotvec(a.numpy())  # noqa: E731
    R, R0 = torch.from_numpy(rot(r).as_matrix()), torch.from_numpy(rot(root).as_matrix())
    np.testing.assert_allclose(t[0], anchor_t, atol=1e-12)
    # every frame leans from the capture's up as it leaned from the motion's
    np.testing.assert_allclose(R[:, :, 1] @ up, R0[:, :, 1] @ motion_up, atol=1e-9)
    # the first frame faces where the anchor faced, about the capture's up
    anchor = torch.from_numpy(rot(anchor_root[None]).as_matrix()[0])
    assert signed_angle(heading(R[0], up), heading(anchor, up), up) == pytest.approx(0.0, abs=1e-9)
    W = Rotation.from_euler("x", -90, degrees=True)  # z-up world
    root_w = torch.from_numpy((W * rot(root)).as_rotvec())
    transl_w = torch.from_numpy(W.apply(transl.numpy()) + [5.0, -2.0, 1.0])
    r2, t2 = place(root_w, transl_w, anchor_root, anchor_t, up, torch.from_numpy(W.apply(motion_up.numpy())))
    np.testing.assert_allclose(rot(r2).as_matrix(), rot(r).as_matrix(), atol=1e-9)
    np.testing.assert_allclose(t2, t, atol=1e-9)
    # the motion's own relative movement is kept: distances between its root positions, its relative turns
    np.testing.assert_allclose(torch.cdist(t, t), torch.cdist(transl, transl), atol=1e-9)
    rel = lambda a: (rot(a[:1]).inv() * rot(a)).magnitude()  # noqa: E731
    np.testing.assert_allclose(rel(r), rel(root), atol=1e-9)


def test_a_motion_that_starts_with_a_bow_still_stands_upright():
    """Frame 0 bows 40° forwards, the rest stand: aligning frame 0 with an upright anchor (the rigid
    first-frame placement) would tilt the standing frames by 40°; the up-aligned one keeps them upright,
    and the lift puts the lowest joint of most frames on the capture's floor."""
    y = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    x = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    bow = rotation_matrix_to_axis_angle(axis_angle_matrix(x, math.radians(40.0))[None])[0]
    root = torch.zeros(5, 3, dtype=torch.float64)
    root[0] = bow
    transl = torch.zeros(5, 3, dtype=torch.float64)
    r, t = place(root, transl, torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), y, y)
    ups = torch.from_numpy(Rotation.from_rotvec(r.numpy()).as_matrix())[:, :, 1]
    assert [round(angle_deg(u, y), 6) for u in ups] == [40.0, 0.0, 0.0, 0.0, 0.0]
    joints = torch.tensor([[[0.0, 0.9, 0.0], [0.0, 0.05, 0.1]]], dtype=torch.float64).repeat(5, 1, 1) + t[:, None]
    joints[2, :, 1] += 0.4  # a jump
    lifted, lift = onto_floor(t, joints, y, floor=-0.3)
    assert lift == pytest.approx(-0.35)
    assert float((joints[:, :, 1] + lift).amin(1).median()) == pytest.approx(-0.3)
    np.testing.assert_allclose(lifted - t, torch.tensor([[0.0, -0.35, 0.0]]).double().expand(5, 3), atol=1e-12)


def test_a_pickle_named_npz_is_refused(tmp_path, anny):
    import pickle

    (tmp_path / "p.npz").write_bytes(pickle.dumps({"poses": np.zeros((2, 156))}))
    with pytest.raises(DeltaError, match=r"p\.npz: not a readable npz file \(a pickle\)"):
        read_motion(tmp_path / "p.npz", *skeleton(anny))
