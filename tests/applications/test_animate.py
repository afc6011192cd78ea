"""A tiny trained avatar driven by motions: its own motion reproduces its own renders, an AMASS-style archive
runs end to end through ``delta animate`` at the capture's whole-frame size, bad inputs get clear errors."""

import json

import cv2
import numpy as np
import pytest
import torch
import trimesh

from delta import DeltaError
from delta.applications.animate import animate_avatar, drive
from delta.applications.motion import Motion
from delta.applications.settings import AnimateSettings
from delta.cli import main
from delta.data.frames import load_full_frames
from delta.export.video import baked_trajectory, capture_upright, to_bgr
from delta.models.image import full_view, render_image
from delta.training.run import load_trained
from tests.export.test_animated_glb import read_glb, skinned

pytestmark = pytest.mark.slow


def test_driving_an_avatar_with_its_own_motion_reproduces_its_renders(tiny_trained):
    """The motion the avatar was trained in, anchored at its first frame, renders each frame as the avatar's own
    render of that frame (the pinhole capture: one camera for every frame)."""
    inputs = tiny_trained["tight"]
    tr = load_trained(inputs["model"], inputs["record"], inputs["body"])
    model = tr.model
    assert model.pinhole and model.trajectory is None
    frames = [0, 2, len(tr.data.frame_ids) - 1]
    up = capture_upright(model).up.numpy()  # its own world's up, as the fit's params.npz carries it
    own = Motion(model.poses.detach().double().numpy()[frames], model.transl.detach().double().numpy()[frames],
                 30.0, "body model", up)  # fmt: skip
    view = full_view(load_full_frames(inputs["record"], [0]), model.resolution)
    with baked_trajectory(model, frames[0]):
        driven = list(drive(model, frames[0], own, view, None, None))
    before = model.poses.detach().clone()
    for k, f in enumerate(frames):
        with torch.no_grad():
            expected = to_bgr(render_image(model, f, view=view, soft_silhouette=False)["rgb"])
        diff = np.abs(driven[k].astype(int) - expected.astype(int))
        assert diff.max() <= 1, (f, diff.max())
    # and the anchor frame's own parameters are back as they were
    assert torch.equal(model.poses.detach(), before)
    assert expected.std() > 0  # a render, not a blank frame


def amass_file(path, frames: int = 5) -> str:
    """An AMASS-style SMPL+H archive at 60 fps: the arms lowered from the T-pose while the body walks forward."""
    poses = np.zeros((frames, 52, 3))
    s = np.linspace(0, 1, frames)
    poses[:, 16, 2] = -1.2 * s  # left shoulder
    poses[:, 17, 2] = 1.2 * s
    poses[:, 0, 0] = np.pi / 2  # z-up world: the pelvis turned upright
    trans = np.stack([0 * s, 0.3 * s, 0.9 + 0 * s], -1)
    np.savez(path, poses=poses.reshape(frames, -1), trans=trans, mocap_framerate=np.array(60.0),
             gender=np.array("neutral"), betas=np.zeros(16))  # fmt: skip
    return str(path)


def test_an_amass_archive_drives_the_avatar_through_the_command(tiny_trained, tmp_path):
    inputs = tiny_trained["tight"]
    motion = amass_file(tmp_path / "walk.npz", frames=10)
    out = tmp_path / "anim"
    code = main(["animate", "--model", inputs["model"], "--record", inputs["record"], "--body", inputs["body"],
                 "--motion", motion, "--out", str(out), "--fps", "30", "--max-frames", "4", "--meshes", "true"])  # fmt: skip
    assert code == 0
    about = json.loads((out / "animation.json").read_text())
    full = load_full_frames(inputs["record"], [0])
    W, H = full.size
    assert about["frames"] == 4 and about["motion_kind"] == "smplh" and about["fps"] == 30.0
    assert about["resolution"] == f"{W}x{H}"
    video = cv2.VideoCapture(str(out / "animation.mp4"))
    got = []
    while True:
        ok, img = video.read()
        if not ok:
            break
        got.append(img)
    assert len(got) == 4 and got[0].shape == (H, W, 3)
    assert np.abs(got[0].astype(int) - got[-1].astype(int)).mean() > 0.5  # the arms came down
    assert sorted(p.name for p in (out / "meshes").iterdir()) == [f"body_{k:05d}.ply" for k in range(4)]
    # the GLB plays the same motion: its key k is the written body mesh of frame k, in its upright world
    doc, arrays = read_glb((out / "animation.glb").read_bytes())
    assert about["glb"]["frames"] == 4 and len(arrays[doc["animations"][0]["samplers"][0]["input"]]) == 4
    world = np.array(doc["nodes"][0]["matrix"]).reshape(4, 4).T
    for k in (0, 3):
        mesh = trimesh.load(out / "meshes" / f"body_{k:05d}.ply", process=False)
        back = (skinned(doc, arrays, k) - world[:3, 3]) @ world[:3, :3]
        np.testing.assert_allclose(back, mesh.vertices, atol=2e-3)


def test_bad_requests_get_clear_errors(tiny_trained, tmp_path):
    inputs = tiny_trained["tight"]
    motion = amass_file(tmp_path / "m.npz")
    with pytest.raises(DeltaError, match="anchor: frame 999 is not a frame of the capture"):
        animate_avatar(inputs["model"], inputs["record"], inputs["body"], motion, tmp_path / "a",
                       AnimateSettings(anchor=999))  # fmt: skip
    with pytest.raises(DeltaError, match="no such model file"):
        animate_avatar(
            tmp_path / "none.pt", inputs["record"], inputs["body"], motion, tmp_path / "a", AnimateSettings()
        )
    np.savez(tmp_path / "short.npz", poses=np.zeros((3, 40)))
    assert main(["animate", "--model", inputs["model"], "--record", inputs["record"], "--body", inputs["body"],
                 "--motion", str(tmp_path / "short.npz"), "--out", str(tmp_path / "b")]) == 2  # fmt: skip
    assert not (tmp_path / "b" / "animation.mp4").exists()
