"""Synthetic captures: determinism, mask/mesh consistency, keypoints, layout, non-rigid motion."""

import hashlib
import json

import cv2
import h5py
import numpy as np
import pytest
import torch

from delta.body.keypoints import openpose18_map
from delta.body.lbs import lbs, skin
from delta.body.model import load_body_model
from delta.cameras.models import OrthographicCamera, PinholeCamera
from delta.data.peoplesnapshot import iter_masks, read_camera, read_keypoints
from delta.synthetic.generate import generate
from delta.synthetic.spec import parse_subject
from tests.conftest import TINY_SUBJECTS

pytestmark = pytest.mark.slow


def gt_camera(params):
    if str(params["camera_model"]) == "pinhole":
        t = lambda k: torch.from_numpy(params[k])  # noqa: E731
        return PinholeCamera(t("K"), t("R"), t("t"), t("dist"), int(params["width"]), int(params["height"]))
    return OrthographicCamera(torch.tensor(params["ortho_scale"][0]), torch.from_numpy(params["ortho_trans"][0]),
                              int(params["width"]), int(params["height"]))  # fmt: skip


def load_params(capture):
    with np.load(capture / "gt" / "params.npz", allow_pickle=False) as p:
        return {k: p[k] for k in p.files}


def rasterise(vertices, faces, camera):
    """Independent oracle: pixel centres inside any projected triangle (edge functions, vectorised)."""
    uv, _ = camera.project(torch.from_numpy(vertices.astype(np.float64)))
    tri = uv.numpy()[faces] - 0.5  # pixel centres at integer coordinates
    lo = np.ceil(tri.min(1)).astype(int)
    hi = np.floor(tri.max(1)).astype(int)
    size = int((hi - lo).max()) + 1
    mask = np.zeros((camera.height, camera.width), np.uint8)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]

    def edge(p, q, x):
        return (q[:, 0] - p[:, 0]) * (x[..., 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (x[..., 0] - p[:, 0])

    for dy in range(size):
        for dx in range(size):
            x = (lo + np.array([dx, dy])).astype(np.float64)
            e0, e1, e2 = edge(a, b, x), edge(b, c, x), edge(c, a, x)
            inside = ((e0 >= 0) & (e1 >= 0) & (e2 >= 0)) | ((e0 <= 0) & (e1 <= 0) & (e2 <= 0))
            inside &= (x[:, 0] <= hi[:, 0]) & (x[:, 1] <= hi[:, 1])
            inside &= (x[:, 0] >= 0) & (x[:, 1] >= 0) & (x[:, 0] < camera.width) & (x[:, 1] < camera.height)
            px = x[inside].astype(int)
            mask[px[:, 1], px[:, 0]] = 1
    return mask


def digest(root):
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}  # fmt: skip


def test_same_spec_and_seed_give_identical_bytes(tmp_path, tiny_captures, anny_files):
    spec = parse_subject("loose", TINY_SUBJECTS["loose"])
    generate(spec, anny_files["body"], tmp_path / "loose", anny_files["shape_space"], anny_files["cache"])
    ref = {k: v for k, v in digest(tiny_captures / "loose").items()}
    assert digest(tmp_path / "loose") == ref
    assert "loose.mp4" in ref and "gt/frames.h5" in ref and "gt/params.npz" in ref


def test_another_seed_changes_the_capture(tmp_path, tiny_captures, anny_files):
    raw = dict(TINY_SUBJECTS["loose"], seed=3)
    generate(parse_subject("loose", raw), anny_files["body"], tmp_path / "loose", anny_files["shape_space"],
             anny_files["cache"])  # fmt: skip
    assert digest(tmp_path / "loose")["loose.mp4"] != digest(tiny_captures / "loose")["loose.mp4"]


@pytest.mark.parametrize("subject", ["tight", "loose"])
def test_masks_are_the_projection_of_the_meshes(tiny_captures, subject):
    capture = tiny_captures / subject
    camera = gt_camera(load_params(capture))
    with h5py.File(capture / "gt" / "meshes.h5") as mh, h5py.File(capture / "gt" / "frames.h5") as fh:
        layers = json.loads(mh.attrs["layers"])
        for f in range(fh["person"].shape[0]):
            verts = [mh["body_vertices"][f]] + [mh[f"{n}_vertices"][f] for n in layers]
            faces = [mh["body_faces"][:]] + [mh[f"{n}_faces"][:] for n in layers]
            offsets = np.cumsum([0] + [len(v) for v in verts[:-1]])
            oracle = rasterise(np.concatenate(verts), np.concatenate([fc + o for fc, o in zip(faces, offsets)]), camera)
            person = fh["person"][f]
            iou = (oracle & person).sum() / (oracle | person).sum()
            assert iou > 0.97, f"frame {f}: IoU {iou:.3f}"
            # part masks lie inside the person mask and partition it with the labels
            for part in ("clothing", "skin", "hair"):
                assert not (fh[part][f] & ~person.astype(bool)).any()
            assert ((fh["clothing"][f] + fh["skin"][f] + fh["hair"][f]) == person).all()
            np.testing.assert_array_equal(person, fh["labels"][f] > 0)
            assert np.isfinite(fh["depth"][f][person > 0]).all() and np.isinf(fh["depth"][f][person == 0]).all()


def test_masks_show_each_layer(tiny_captures):
    with h5py.File(tiny_captures / "tight" / "gt" / "frames.h5") as fh:
        assert fh["clothing"][0].sum() > 0.3 * fh["person"][0].sum()
        assert fh["skin"][0].sum() > 0.1 * fh["person"][0].sum()
    with h5py.File(tiny_captures / "loose" / "gt" / "frames.h5") as fh:
        assert fh["hair"][:].sum() > 0


@pytest.mark.parametrize("subject", ["tight", "loose"])
def test_gt_joints_project_onto_gt_keypoints(tiny_captures, anny_files, subject):
    capture = tiny_captures / subject
    params = load_params(capture)
    camera = gt_camera(params)
    model = load_body_model(anny_files["body"], dtype=torch.float64)
    out = lbs(model, torch.from_numpy(params["betas"])[None].expand(len(params["poses"]), -1),
              torch.from_numpy(params["poses"]), transl=torch.from_numpy(params["transl"]))  # fmt: skip
    kp3d = openpose18_map(model)(out.joints, out.vertices)
    uv, _ = camera.project(kp3d)
    with h5py.File(capture / "gt" / "frames.h5") as fh:
        kp = fh["keypoints"][:]
        np.testing.assert_allclose(fh["keypoints3d"][:], kp3d.numpy(), atol=1e-5)
    np.testing.assert_allclose(kp[..., :2], uv.numpy(), atol=1e-3)
    knee = model.joint_names.index("lowerleg01.L")
    np.testing.assert_allclose(
        kp[:, 12, :2], camera.project(out.joints[:, knee : knee + 1])[0][:, 0].numpy(), atol=1e-3
    )
    assert set(np.unique(kp[..., 2]).tolist()) <= {0.0, np.float32(0.3).item(), 1.0}
    assert (kp[0, :, 2] == 1.0).mean() > 0.7  # the first frame faces the camera


def test_peoplesnapshot_layout_reads_back(tiny_captures):
    capture = tiny_captures / "tight"
    ps = tiny_captures / "ps" / "tight"
    params = load_params(capture)
    cam = read_camera(ps / "camera.pkl").to_pinhole()
    ref = gt_camera(params)
    for a, b in ((cam.K, ref.K), (cam.R, ref.R), (cam.t, ref.t), (cam.dist, ref.dist)):
        torch.testing.assert_close(a, b)
    with h5py.File(capture / "gt" / "frames.h5") as fh:
        person = fh["person"][:]
        kp = fh["keypoints"][:]
    masks = list(iter_masks(ps / "masks.hdf5"))
    assert len(masks) == len(person) == len(read_keypoints(ps / "keypoints.hdf5"))
    np.testing.assert_array_equal(np.stack(masks), person)
    np.testing.assert_allclose(read_keypoints(ps / "keypoints.hdf5"), kp, atol=1e-6)
    assert (ps / "tight.mp4").read_bytes() == (capture / "tight.mp4").read_bytes()
    cap = cv2.VideoCapture(str(ps / "tight.mp4"))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == len(person)


def test_video_frames_match_masks(tiny_captures):
    """The (lossless) video shows the person exactly where the mask says, background elsewhere."""
    capture = tiny_captures / "tight"
    spec = parse_subject("tight", TINY_SUBJECTS["tight"])
    cap = cv2.VideoCapture(str(capture / "tight.mp4"))
    ok, frame = cap.read()
    assert ok and frame.shape == (128, 128, 3)
    with h5py.File(capture / "gt" / "frames.h5") as fh:
        alpha = fh["alpha"][0]
    bg = np.round(np.array(spec.background)[::-1] * 255)
    np.testing.assert_array_equal(frame[alpha == 0], np.broadcast_to(bg, frame[alpha == 0].shape))
    assert (np.abs(frame[alpha == 255].astype(int) - bg).sum(-1) > 0).mean() > 0.95


def test_dress_sways_beyond_skinning(tiny_captures, anny_files):
    """The dress's posed vertices = skinned canonical + a non-rigid part that grows towards the hem."""
    capture = tiny_captures / "loose"
    params = load_params(capture)
    model = load_body_model(anny_files["body"], dtype=torch.float64)
    with h5py.File(capture / "gt" / "meshes.h5") as mh:
        canon = torch.from_numpy(mh["dress_canonical"][:].astype(np.float64))
        posed = mh["dress_vertices"][:]
    out = lbs(model, torch.from_numpy(params["betas"])[None].expand(len(posed), -1), torch.from_numpy(params["poses"]))
    root_only = torch.zeros(len(canon), model.num_joints, dtype=torch.float64)
    root_only[:, 0] = 1.0
    rigid, _ = skin(canon[None].expand(len(posed), -1, -1), root_only, out.joint_transforms)
    diff = np.linalg.norm(posed - rigid.numpy(), axis=-1)
    hem = canon[:, 1] < canon[:, 1].min() + 0.05
    assert diff[:, hem.numpy()].mean() > 0.01  # centimetres of sway at the hem


def test_splits_partition_the_frames(tiny_captures):
    s = json.loads((tiny_captures / "tight" / "gt" / "splits.json").read_text())
    frames = s["train"] + s["test_view"] + s["test_pose"]
    assert sorted(frames) == list(range(7)) and len(set(frames)) == 7
    assert s["test_view"] == [1, 3] and s["test_pose"] == [5, 6]


def test_cli_in_a_fresh_process_reproduces_the_bytes(tmp_path, tiny_captures, anny_files):
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "delta.cli", "synthesize", "--subject", "tight", "--settings",
           json.dumps(TINY_SUBJECTS["tight"]), "--body", anny_files["body"], "--shape-space",
           anny_files["shape_space"], "--anny-cache", anny_files["cache"], "--out", str(tmp_path / "tight")]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    ref = digest(tiny_captures / "tight")
    assert digest(tmp_path / "tight") == ref


def test_an_upper_framing_shows_no_legs_and_the_capture_says_so(tmp_path, anny_files):
    """A head-and-shoulders capture: the chest runs off the bottom edge in every frame, hips and legs
    are never seen (keypoint confidence 0), the record's crop ends at the image's bottom edge, and
    training's capture detection picks 'upper' from the ground-truth body."""
    from delta.data.record import FrameRecord
    from delta.data.sources import synthetic_source
    from delta.preprocess.frames import prepare
    from delta.scene.framing import detect_capture

    raw = dict(seed=4, garments=["tshirt"], hair="long", camera="pinhole", framing="upper", resolution=96,
               turn_frames=3, novel_frames=1, test_view_every=2)  # fmt: skip
    generate(parse_subject("head", raw), anny_files["body"], tmp_path / "head", anny_files["shape_space"],
             anny_files["cache"])  # fmt: skip
    model = load_body_model(anny_files["body"])
    with h5py.File(tmp_path / "head" / "gt" / "frames.h5") as g:
        person, kp = g["alpha"][:] > 0, g["keypoints"][:]
    assert person[:, -1].any(1).all() and not person[:, 0].any(), "cut at the bottom, head in view"
    names = openpose18_map(model).names
    legs = [i for i, n in enumerate(names) if n.split("_")[-1] in ("hip", "knee", "ankle")]
    assert len(legs) == 6 and (kp[:, legs, 2] == 0).all()
    # the init fit's silhouette balance reads no legs in view: the outline the image's edge cuts is not weighed up
    from delta.fitting.balance import MIN_LEGS_SEEN, legs_seen, silhouette_balance
    from delta.fitting.settings import FitConfig

    seen = legs_seen(torch.from_numpy(kp), FitConfig().conf_threshold)
    assert seen == 0.0 < MIN_LEGS_SEEN
    scattered = torch.full((len(kp),), 10.0)  # hands off the frame: keypoints far from any fitted body
    assert (
        silhouette_balance(scattered, torch.zeros(len(kp), dtype=torch.bool), 96, FitConfig(), legs=seen)["factor"] == 1
    )
    nose = names.index("nose")
    assert (kp[:, nose, 2] > 0).any()
    record = tmp_path / "head.h5"
    prepare(synthetic_source(tmp_path / "head", "head"), record, size=64)
    with FrameRecord(record) as rec:
        cam, n = rec.camera(), rec.size
        assert rec.h5["person"][:, -1].any(1).all(), "the crop keeps the cut at its bottom edge"
    p = load_params(tmp_path / "head")
    ids = np.arange(len(p["poses"]))
    capture = detect_capture(model, torch.from_numpy(p["betas"]).float(), torch.from_numpy(p["poses"]).float(),
                             torch.from_numpy(p["transl"]).float(), cam, ids, n)  # fmt: skip
    assert capture == "upper"
