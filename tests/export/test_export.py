"""The export of a tiny trained avatar: files load back, line up with the renders, videos play; bad inputs."""

import dataclasses
import json

import cv2
import numpy as np
import pymeshlab
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree
from torch import nn

from delta.cli import main
from delta.export import lineup
from delta.export.meshes import MeshPart, body_mesh, clothing_nerf_space, edge_lengths, pose_clothing
from delta.export.run import export_trained, novel_pose_frames, rendered_hits, report_frames, silhouette
from delta.models.image import render_image
from delta.training.run import load_trained
from tests.export.conftest import SETTINGS

pytestmark = pytest.mark.slow
SHELL = 0.06
"""Thickness (m) of the analytic clothing: everything within this distance of the canonical body."""
RAMP = 0.02


class ShellNeRF(nn.Module):
    """An analytic exterior, red: density 4000/m within ``SHELL`` of the canonical template vertices, falling
    linearly to 0 over ``RAMP`` around that distance (a step would put the marching-cubes level anywhere in a cell)."""

    def __init__(self, canonical: torch.Tensor):
        super().__init__()
        self.tree = cKDTree(canonical.detach().cpu().numpy())

    def color_cell(self) -> float:
        return 0.01  # the export splits the clothing's edges down to half this and no further

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        d, _ = self.tree.query(x.detach().cpu().numpy(), k=1)
        sigma = torch.from_numpy(4000.0 * np.clip((SHELL - d) / RAMP + 0.5, 0, 1)).to(x)
        return x.new_tensor([1.0, 0.0, 0.0]).expand(len(x), 3), sigma


class Part(ShellNeRF):
    """The analytic shell, ``colour``, only above (hair) or below (clothing) ``neck`` in canonical height."""

    def __init__(self, canonical: torch.Tensor, colour, neck: float, hair: bool):
        super().__init__(canonical)
        self.colour, self.neck, self.hair = torch.tensor(colour), neck, hair

    def forward(self, x):
        _, sigma = super().forward(x)
        keep = (x[:, 1] > self.neck) if self.hair else (x[:, 1] <= self.neck)
        return self.colour.to(x).expand(len(x), 3), sigma * keep.to(sigma)

    def density(self, x):
        return self.forward(x)[1]


def layered(model, clothing_colour, hair_colour):
    """The avatar's exterior replaced by analytic clothing and hair layers around its canonical body."""
    from delta.fields.networks import LayeredNeRF

    cano = (model.canonical_T[..., :3] @ model.body.v_template[..., None]).squeeze(-1) + model.canonical_T[..., 3]
    neck = float(cano[:, 1].max()) - 0.25
    model.nerf = LayeredNeRF.of({"clothing": Part(cano, clothing_colour, neck, False),
                                 "hair": Part(cano, hair_colour, neck, True)})  # fmt: skip
    model.occupancy = None
    model.spec.render.samples, model.spec.render.max_dist = 32, 0.12
    return neck


@pytest.fixture(scope="module")
def shell_avatar(tiny_model):
    """The tiny trained avatar with the analytic shell as its NeRF, 24 samples per ray (a thin shell)."""
    tr = load_trained(tiny_model["model"], tiny_model["record"], tiny_model["body"])
    cano_T, template = tr.model.canonical_T, tr.model.body.v_template
    tr.model.nerf = ShellNeRF((cano_T[..., :3] @ template[..., None]).squeeze(-1) + cano_T[..., 3])
    tr.model.deformation = None
    tr.model.spec.render.samples = 24
    return tr


@pytest.fixture(scope="module")
def shell_export(shell_avatar, tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    return out, export_trained(shell_avatar, out, SETTINGS, {"model": "tiny"})


def test_exported_meshes_load_back_and_the_body_is_watertight(shell_export, shell_avatar):
    out, summary = shell_export
    model = shell_avatar.model
    for name in ("body_canonical", "body_posed", "clothing_canonical", "clothing_posed", "clothing_nerf_space"):
        tm = trimesh.load(out / f"{name}.ply", process=False)
        ms = pymeshlab.MeshSet()
        ms.load_new_mesh(str(out / f"{name}.ply"))
        assert ms.current_mesh().face_number() == len(tm.faces) > 0, name
        assert ms.current_mesh().has_vertex_color(), name
    body = trimesh.load(out / "body_posed.ply", process=False)
    assert body.is_watertight and summary["body"]["watertight"]
    expected, _ = body_mesh(model, summary["posed_frame"])
    np.testing.assert_allclose(body.vertices, expected.vertices, atol=1e-5)
    np.testing.assert_array_equal(body.faces, model.body.faces.numpy())
    albedo = model.albedo().detach().numpy()
    np.testing.assert_allclose(body.visual.vertex_colors[:, :3] / 255, albedo, atol=0.5 / 255 + 1e-6)
    # the analytic shell's colour, its thickness around the canonical body
    cloth = trimesh.load(out / "clothing_canonical.ply", process=False)
    assert (cloth.visual.vertex_colors[:, :3] == [255, 0, 0]).all()
    canonical_body = trimesh.load(out / "body_canonical.ply", process=False)
    d, _ = cKDTree(canonical_body.vertices).query(cloth.vertices)
    assert abs(np.median(d) - SHELL) < 0.3 * SHELL, np.median(d)


def test_clothing_colours_are_read_a_capture_pixel_apart_or_half_the_nerfs_cell(shell_export, shell_avatar):
    out, summary = shell_export
    model, sampling = shell_avatar.model, summary["colour_sampling"]
    body, _ = body_mesh(model, summary["posed_frame"])
    # no record given: the capture is the model's own crop, an orthographic camera (2 / (s W) a pixel)
    pixel_mm = 2000.0 / (float(model.camera(summary["posed_frame"]).scale.detach()) * model.resolution)
    assert sampling["capture_pixel_mm"] == pytest.approx(pixel_mm, abs=0.01)
    longest = max(SETTINGS.color_spacing * pixel_mm, 5.0)
    assert sampling["clothing_longest_edge_mm"] == pytest.approx(longest, abs=0.01)
    cloth = _part(out / "clothing_nerf_space.ply")
    assert edge_lengths(cloth).max() * 1000 <= longest + 1e-6
    assert sampling["clothing_edges"]["p95_mm"] <= longest


def test_glb_holds_body_and_clothing(shell_export):
    out, summary = shell_export
    scene = trimesh.load(out / "avatar.glb")
    assert isinstance(scene, trimesh.Scene)
    assert set(scene.geometry) == {"body", "clothing"}
    assert len(scene.geometry["body"].faces) == summary["body"]["faces"]
    assert len(scene.geometry["clothing"].faces) == summary["clothing"]["faces"]


def test_the_animated_glb_plays_the_capture_upright_on_its_floor(shell_export, shell_avatar):
    """Read back and skinned by glTF's rules: at the posed frame's key the body is body_posed.ply and the
    clothing clothing_posed.ply (its weights borrowed from the nearest body vertices), in the upright world."""
    from delta.export.animated import world_transform
    from delta.export.video import capture_upright
    from tests.export.test_animated_glb import read_glb, skinned

    out, summary = shell_export
    model, data = shell_avatar.model, shell_avatar.data
    doc, arrays = read_glb((out / "avatar_animated.glb").read_bytes())
    frames = sorted(set(data.frame_ids.tolist()))
    assert summary["animated"]["frames"] == len(frames) and [m["name"] for m in doc["meshes"]] == ["body", "clothing"]
    world = np.array(doc["nodes"][0]["matrix"]).reshape(4, 4).T
    up = capture_upright(model)
    np.testing.assert_allclose(world[:3, :3] @ up.up.numpy(), [0, 1, 0], atol=1e-6)
    key = frames.index(int(data.frame_ids[summary["posed_frame"]]))
    back = lambda v: (v - world[:3, 3]) @ world[:3, :3]  # noqa: E731  (the capture's world again)
    body = trimesh.load(out / "body_posed.ply", process=False)
    np.testing.assert_allclose(back(skinned(doc, arrays, key, 0)), body.vertices, atol=2e-3)
    cloth = trimesh.load(out / "clothing_posed.ply", process=False)
    err = np.linalg.norm(back(skinned(doc, arrays, key, 1)) - cloth.vertices, axis=1)
    assert np.median(err) < 0.01  # kNN forward skinning vs the nearest vertices' weights: close, not equal
    # standing on y = 0: the soles of the frames, by the median, are on the floor
    lowest = [skinned(doc, arrays, k, 0)[:, 1].min() for k in range(len(frames))]
    assert abs(float(np.median(lowest))) < 0.015
    assert world_transform(up, np.zeros(3), 0.05)[1, 3] == pytest.approx(0.05 - up.floor)


def test_videos_and_images_have_the_right_frames_and_size(shell_export, shell_avatar):
    out, summary = shell_export
    n, split = shell_avatar.model.resolution, shell_avatar.data.split
    for name, count in (("turntable", SETTINGS.turntable_frames), ("novel_pose", len(novel_pose_frames(split)))):
        cap = cv2.VideoCapture(str(out / f"{name}.mp4"))
        frames = []
        ok, img = cap.read()
        while ok:
            frames.append(img)
            ok, img = cap.read()
        cap.release()
        assert len(frames) == count == summary[name]["frames"], name
        assert frames[0].shape == (n, n, 3)
    # the turntable turns: the first and the middle frames differ, the avatar stays in view (red clothing)
    pngs = sorted((out / "sidebyside").glob("*.png"))
    assert len(pngs) == len(report_frames(split, SETTINGS.sidebyside)) == len(summary["frames"])
    img = cv2.imread(str(pngs[0]))
    assert img.shape == (n, 3 * n, 3)
    assert summary["turntable"]["frames"] == SETTINGS.turntable_frames
    json.loads((out / "export.json").read_text())


def test_exported_meshes_line_up_with_the_renders(shell_export, shell_avatar):
    out, summary = shell_export
    assert summary["lineup"]["iou_body"] > 0.99  # the same mesh, rasterised vs ray-cast
    assert summary["lineup"]["iou_avatar"] > 0.9, summary["frames"]
    # the files themselves, projected, against the rendered masks; and the clothing matters
    model, frame = shell_avatar.model, summary["posed_frame"]
    img = render_image(model, frame)
    rendered = rendered_hits(model, frame) | (img["nerf_mask"].numpy() > 0.5)
    body, cloth = (_part(out / f"{name}_posed.ply") for name in ("body", "clothing"))
    both = silhouette(model, frame, [body, cloth])
    assert lineup.iou(both, rendered) == pytest.approx(summary["frames"][0]["iou_avatar"], abs=2e-4)
    assert lineup.iou(silhouette(model, frame, [body]), rendered) < lineup.iou(both, rendered) - 0.1


def _part(path) -> MeshPart:
    tm = trimesh.load(path, process=False)
    return MeshPart(np.asarray(tm.vertices, dtype=np.float64), np.asarray(tm.faces), np.zeros((len(tm.vertices), 3)))


def test_turntable_turns_and_leaves_the_model_unchanged(shell_avatar):
    from delta.body.upright import Upright
    from delta.export.video import turntable

    model = shell_avatar.model
    before = (model.poses.detach().clone(), model.transl.detach().clone())
    # a capture whose up is the (orthographic) camera's vertical: no levelling, a turn about the image's vertical
    level = Upright(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), 0.0, 0.0, 1)
    frames = list(turntable(model, 0, 2, upright=level))
    assert torch.equal(model.poses, before[0]) and torch.equal(model.transl, before[1])
    still = cv2.cvtColor((render_image(model, 0)["rgb"].numpy() * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR)
    assert np.abs(frames[0].astype(int) - still.astype(int)).max() <= 1  # angle 0: the frame itself
    # half a turn seen by the orthographic camera: the silhouette mirrors about the body's centre column
    assert not model.pinhole
    verts = model.pose_body(0).vertices[0].detach()
    u_c = float(model.camera(0).project(verts.mean(0)[None])[0][0, 0].detach())
    n = model.resolution
    front, back = (still < 250).any(-1), (frames[1] < 250).any(-1)

    def mirrored(about: float) -> np.ndarray:
        src = np.round(2 * about - np.arange(n) - 1).astype(int)  # the column j mirrors: u = j + 0.5 -> 2 u_c - u
        inside = (src >= 0) & (src < n)
        out = np.zeros_like(front)
        out[:, inside] = front[:, src[inside]]
        return out

    assert lineup.iou(mirrored(u_c), back) > 0.85
    # about the body's centre, not another column
    assert max(lineup.iou(mirrored(u_c + d), back) for d in (-4, 4)) < lineup.iou(mirrored(u_c), back) - 0.05


def test_posed_clothing_follows_the_body(shell_export, shell_avatar):
    """The garment's sheet stays its thickness off the body in every pose: no vertex lies on the skin (the
    wall the density's cut at the skin makes is not exported)."""
    out, _ = shell_export
    model = shell_avatar.model
    cloth = _part(out / "clothing_nerf_space.ply")
    for frame in (0, len(shell_avatar.data.split) - 1):
        body, lbs_out = body_mesh(model, frame)
        d, _ = cKDTree(body.vertices).query(pose_clothing(model, cloth, lbs_out).vertices)
        assert abs(np.median(d) - SHELL) < 0.3 * SHELL
        assert np.quantile(d, 0.02) > 0.5 * SHELL


def test_the_meshes_and_the_videos_export_apart_as_together(shell_export, shell_avatar, tmp_path):
    """``--part meshes`` writes the meshes and no video; ``--part videos`` then reads them (the line-up
    check poses the clothing file) and writes what one whole export writes; videos alone are refused."""
    from delta import DeltaError

    whole_dir, whole = shell_export
    with pytest.raises(DeltaError, match="meshes.json: missing; the videos part reads the meshes part's output"):
        export_trained(shell_avatar, tmp_path / "none", SETTINGS, part="videos")
    out = tmp_path / "apart"
    meshes = export_trained(shell_avatar, out, SETTINGS, {"model": "tiny"}, part="meshes")
    assert (out / "meshes.json").is_file() and not (out / "export.json").exists()
    assert not (out / "turntable.mp4").exists() and (out / "avatar_animated.glb").stat().st_size > 0
    assert "grid" in meshes["settings"] and "turntable_frames" not in meshes["settings"]
    videos = export_trained(shell_avatar, out, SETTINGS, part="videos")
    assert json.loads((out / "export.json").read_text()) == json.loads(json.dumps(videos))
    for key in ("body", "clothing", "colour_sampling", "upright", "animated", "posed_frame", "model"):
        assert videos[key] == whole[key], key
    assert videos["settings"] == vars(SETTINGS) == whole["settings"]
    # the clothing read back from its PLY lines up as the one made in the same process
    for mine, theirs in zip(videos["frames"], whole["frames"]):
        assert mine["iou_avatar"] == pytest.approx(theirs["iou_avatar"], abs=1e-3)
        assert mine["iou_body"] == theirs["iou_body"] and mine["psnr"] == theirs["psnr"]
    for name in ("turntable.mp4", "novel_pose.mp4", "clothing_nerf_space.ply", "avatar.glb"):
        assert (out / name).stat().st_size > 0, name
    assert set(videos["seconds"]) >= {"meshes", "videos", "total", "turntable"}
    # the clothing file gone, where the meshes' summary says there is one: named
    (out / "clothing_nerf_space.ply").unlink()
    with pytest.raises(DeltaError, match="clothing_nerf_space.ply: missing, but .* says the clothing mesh has"):
        export_trained(shell_avatar, out, SETTINGS, part="videos")


def test_frame_choice():
    split = np.array([0, 0, 1, 0, 2, 2, 1])
    assert report_frames(split, 2) == [2, 6] and report_frames(split, 10) == [2, 4, 5, 6]
    assert report_frames(np.zeros(3, int), 2) == [0, 2]
    assert novel_pose_frames(split) == [4, 5] and novel_pose_frames(np.zeros(3, int)) == [0, 1, 2]
    assert novel_pose_frames(np.zeros(9, int), at_most=3) == [0, 4, 8] and novel_pose_frames(split, at_most=5) == [4, 5]


# ------------------------------------------------------------------ the CLI
def test_cli_exports_a_model_file(tiny_model, tmp_path, capsys):
    out = tmp_path / "x"
    args = ["export", "--model", tiny_model["model"], "--record", tiny_model["record"], "--body", tiny_model["body"],
            "--out", str(out), "--grid", "24", "--turntable-frames", "2", "--sidebyside", "0"]  # fmt: skip
    assert main(args) == 0
    summary = json.loads((out / "export.json").read_text())
    assert summary["model"] == tiny_model["model"] and summary["turntable"]["frames"] == 2
    assert not list((out / "sidebyside").iterdir()) and len(summary["frames"]) == 1  # line-up on one frame
    for name in ("body_canonical.ply", "body_posed.ply", "avatar.glb", "turntable.mp4", "novel_pose.mp4"):
        assert (out / name).stat().st_size > 0, name
    assert summary["lineup"]["iou_body"] > 0.99


def test_bad_inputs_give_clear_errors(tiny_model, tmp_path, capsys):
    base = ["export", "--record", tiny_model["record"], "--body", tiny_model["body"], "--out", str(tmp_path / "y")]
    assert main(base + ["--model", str(tmp_path / "missing.pt")]) == 2
    assert "missing.pt: no such model file" in capsys.readouterr().err
    other = ["export", "--model", tiny_model["model"], "--record", tiny_model["other_record"],
             "--body", tiny_model["body"], "--out", str(tmp_path / "z")]  # fmt: skip
    assert main(other) == 2
    assert "not the record this model was trained on" in capsys.readouterr().err
    assert main(base + ["--model", tiny_model["model"], "--grid", "2"]) == 2
    assert "export.grid" in capsys.readouterr().err
    assert not (tmp_path / "y").exists() and not (tmp_path / "z").exists()


def test_each_layer_of_a_layered_exterior_is_its_own_mesh(tiny_model):
    """Analytic clothing below the neck and hair above it: each layer's surface lies on its side of the neck
    and the two together are the whole exterior's surface (same faces, up to the cut at the neck)."""
    tr = load_trained(tiny_model["model"], tiny_model["record"], tiny_model["body"])
    neck = layered(tr.model, (0.9, 0.1, 0.1), (0.1, 0.8, 0.2))
    st = dataclasses.replace(SETTINGS, decimate=0, smooth=0)
    whole = clothing_nerf_space(tr.model, st)
    parts = {n: clothing_nerf_space(tr.model, st, 0.0, n) for n in ("clothing", "hair")}
    cell = 0.05  # a grid cell or so of slack at the cut
    assert parts["hair"].vertices[:, 1].min() > neck - cell and parts["clothing"].vertices[:, 1].max() < neck + cell
    np.testing.assert_allclose(parts["hair"].colors, np.tile([0.1, 0.8, 0.2], (len(parts["hair"].colors), 1)))
    np.testing.assert_allclose(parts["clothing"].colors, np.tile([0.9, 0.1, 0.1], (len(parts["clothing"].colors), 1)))
    area = {k: v.to_trimesh().area for k, v in parts.items()}
    assert min(area.values()) > 0.05 and sum(area.values()) == pytest.approx(whole.to_trimesh().area, rel=0.05)


def test_a_layered_exports_files_keep_the_whole_exterior_apart_from_each_layer(tiny_model, tmp_path):
    """clothing_nerf_space.ply stays the whole exterior (what the evaluation scores), each layer is its own
    layer_{name}_*.ply: the clothing layer's file does not overwrite the whole one."""
    tr = load_trained(tiny_model["model"], tiny_model["record"], tiny_model["body"])
    layered(tr.model, (0.9, 0.1, 0.1), (0.1, 0.8, 0.2))
    st = dataclasses.replace(SETTINGS, decimate=0, smooth=0)
    summary = export_trained(tr, tmp_path, st, {"model": "tiny"}, part="meshes")
    area = {k: trimesh.load(tmp_path / f"layer_{k}_nerf_space.ply", process=False).area for k in ("clothing", "hair")}
    whole = trimesh.load(tmp_path / "clothing_nerf_space.ply", process=False)
    assert len(whole.vertices) == summary["clothing"]["vertices"] > summary["layers"]["clothing"]["vertices"]
    assert whole.area > max(area.values()) and min(area.values()) > 0.05
    assert (tmp_path / "layer_hair_canonical.ply").is_file() and (tmp_path / "clothing_canonical.ply").is_file()
    assert all(type(layer).__name__ == "Part" for layer in tr.model.nerf.layers.values())  # the videos: as trained
