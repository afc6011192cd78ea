"""The scene analysis: reach beyond the body (analytic silhouettes), the decisions, and what training takes."""

import json
import shutil

import h5py
import numpy as np
import pytest

from delta.data.frames import BYTES_PER_PIXEL
from delta.scene.analysis import (
    MAX_SAMPLE_FACTOR,
    SAMPLE_PIXELS,
    analyze,
    room_and_samples,
    shell_start,
    stage2_factor,
    step_rays,
    training_resolution,
)
from delta.scene.settings import FRAME_BUDGET, HEAD_SEMANTIC, HEAD_WEIGHTS, scene_settings, set_keys, user_decided
from delta.training.presets import resolve
from delta.scene.reach import beyond_body, region_reach


def test_reach_is_the_distance_to_the_silhouette_charged_to_the_nearest_region():
    body = np.zeros((40, 60), bool)
    body[10:30, 10:30] = True
    regions = np.zeros((40, 60), np.int64)
    regions[:, 20:] = 2  # the body's right half is region 2
    person = body.copy()
    person[15:25, 30:40] = True  # a flap 10 pixels wide to the right of the body
    mpp = np.full((40, 60), 0.01)
    mpp[:, 25:] = 0.02  # farther from the camera on that side: 2 cm a pixel
    b = beyond_body(body, regions, person, mpp)
    assert len(b.metres) == 100 and set(b.region.tolist()) == {2}
    # the column 30 + k is k + 1 pixels from the body's last column (29), at 2 cm a pixel
    np.testing.assert_allclose(np.sort(np.unique(np.round(b.metres, 6))), 0.02 * np.arange(1, 11))
    reach = region_reach([b], {2: "hands"}, percentile=100, min_share=0.0)
    assert reach == {"hands": {"reach_m": 0.2, "pixels": 100}}
    # no body in view: nothing beyond it
    assert len(beyond_body(np.zeros_like(body), regions, person, mpp).metres) == 0


def test_a_region_with_a_stray_pixel_does_not_count():
    body = np.zeros((40, 40), bool)
    body[10:30, 10:20] = True
    regions = np.where(np.arange(40)[:, None] < 11, 1, 0) * np.ones((1, 40), np.int64)
    person = body.copy()
    person[12:28, 20:25] = True  # 80 pixels beside region 0
    person[9, 12] = True  # one stray pixel above region 1
    frames = [beyond_body(body, regions, person, np.full((40, 40), 0.01))]
    assert set(region_reach(frames, {0: "body", 1: "face"}, 98, min_share=0.02)) == {"body"}


def test_room_and_samples_follow_the_reach_from_the_presets_floor():
    assert room_and_samples(0.0, 0.1, 16) == (0.1, 16)  # nothing beyond the body: the preset's own
    assert room_and_samples(0.2, 0.1, 16) == (0.27, 44)  # 0.2 x 1.25 + 0.02 m at the preset's spacing
    assert room_and_samples(5.0, 0.1, 16) == (0.6, 64)  # capped room, at most 4x the samples
    # a full body's 3.85-mm pixels at 512²: 26 samples across the preset's room at one a pixel
    assert room_and_samples(0.0, 0.1, 16, 0.00385 / SAMPLE_PIXELS) == (0.1, 26)


def test_a_head_and_shoulders_exterior_gets_a_shell_at_its_reach_and_a_full_body_none():
    assert shell_start(0.0126, "upper") == 0.016  # 1.26 cm x 1.25
    assert shell_start(0.2, "upper") == 0.25
    assert shell_start(0.0126, "full") == 0.0  # not measured on full bodies: none
    assert shell_start(0.0, "upper") == 0.0  # nothing beyond the body: no shell


def test_the_scenes_shell_reaches_training_where_the_config_is_silent(tmp_path):
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({"decisions": {"render": {"max_dist": 0.1, "shell": 0.016}}}))
    resolved = resolve("fast").raw
    assert scene_settings(scene, resolved, [])["render"] == {"max_dist": 0.1, "shell": 0.016}
    assert scene_settings(scene, resolved, ["render.shell"])["render"] == {"max_dist": 0.1}


@pytest.mark.parametrize("footprint, room", [
    (0.02, 0.1),  # 128² pixels of a full body (2 cm): the preset's spacing is finer already
    (0.00385, 0.1),  # 512² of a full body
    (0.0016, 0.1),  # 512² of a head and shoulders
    (0.0016, 0.27),  # and a dress's room: at most 4x the preset's
    (0.00385, 0.27),
])  # fmt: skip
def test_samples_are_no_sparser_than_the_training_pixels(footprint, room):
    reach = (room - 0.02) / 1.25
    got_room, samples = room_and_samples(reach, 0.1, 16, footprint)
    assert got_room == pytest.approx(room)
    spacing = max(room / samples, room / 64)  # as dense as SAMPLE_PIXELS pixels, unless capped at 4x 16
    assert spacing <= SAMPLE_PIXELS * footprint * (1 + 1e-9) or samples == 64
    assert samples >= max(16, 16 * room / 0.1 - 1e-9)  # never sparser than the preset's spacing
    assert samples - 1 < max(16 * room / 0.1, room / (SAMPLE_PIXELS * footprint)) or samples == 16  # the fewest
    assert room_and_samples(reach, 0.1, 16, footprint / 2)[1] >= samples  # a finer capture: never fewer
    assert room_and_samples(reach, 0.1, 16, 0.0)[1] == room_and_samples(reach, 0.1, 16)[1]  # footprint unknown


@pytest.mark.parametrize("samples", [1, 8, 16, 26, 27, 32, 33, 40, 63, 64, 200])
def test_stage_one_spends_what_its_samples_leave_of_the_costliest_step_on_rays(samples):
    rays = step_rays(samples, 16, 4096, 8192)
    assert 4096 <= rays <= 8192  # between the preset's rays and its most
    costliest = 4096 * MAX_SAMPLE_FACTOR * 16  # the preset's rays at the most samples a scene gets
    assert rays * samples <= costliest or rays == 4096  # never a costlier step than the preset allows
    assert (rays + 1) * samples > costliest or rays == 8192  # and no fewer rays than fit
    assert step_rays(samples + 1, 16, 4096, 8192) <= rays  # more samples a ray: never more rays
    assert step_rays(samples, 16, 4096, 0) == step_rays(samples, 16, 4096, 2048) == 4096  # no room: the preset's


def test_the_scenes_rays_reach_stage_one_only_where_the_config_is_silent(tmp_path):
    assert step_rays(27, 16, 4096, 8192) == 8192  # tight at 512² (27 samples): twice the rays
    assert step_rays(64, 16, 4096, 8192) == 4096  # loose's dress room (64 samples): the preset's
    assert step_rays(40, 16, 4096, 8192) == 6553
    path = tmp_path / "scene.json"
    path.write_text(json.dumps({"decisions": {"stage1": {"rays": 8192}}}))
    fast = {"stage1": {"rays": 4096, "max_rays": 8192}}
    assert scene_settings(path, fast, []) == {"stage1": {"rays": 8192}}
    assert scene_settings(path, fast, ["stage1.rays"]) == {}  # the user's wins
    assert scene_settings(path, fast, ["render.samples"]) == {}  # the user's samples too
    # a run of a preset that allows no more than its own rays (a sweep's balanced variant) keeps them
    assert scene_settings(path, {"stage1": {"rays": 4096}}, []) == {"stage1": {"rays": 4096}}
    assert scene_settings(path, {"stage1": {"rays": 4096, "max_rays": 6000}}, []) == {"stage1": {"rays": 6000}}
    path.write_text(json.dumps({"decisions": {"stage1": {"rays": 4096}}}))  # and one with more keeps its own
    assert scene_settings(path, {"stage1": {"rays": 16384}}, []) == {"stage1": {"rays": 16384}}
    assert user_decided(["stage1.rays"], 2) == [] and user_decided(["stage1.rays"], 1) == ["stage1.rays"]


def test_a_stage_resolves_as_the_workflow_resolves_it_the_configs_keys_over_the_scenes(tmp_path):
    from delta.training.run import stage_settings

    assert set_keys([{"stage1": {"rays": 2048, "lr": {}}, "seed": 1}, {"stage1": {"rays": 1}}]) == [
        "seed", "stage1.lr", "stage1.rays"]  # fmt: skip
    path = tmp_path / "scene.json"
    path.write_text(json.dumps({"decisions": {"stage1": {"rays": 8192}, "render": {"samples": 40}}}))
    over = {"stage1": {"max_rays": 8192}}
    st = stage_settings("balanced", [over], str(path), set_keys([over]))
    assert (st.stage1.rays, st.avatar.render.samples) == (8192, 40)  # the scene's, where the config is silent
    over = {"stage1": {"max_rays": 8192}, "render": {"samples": 24}}
    st = stage_settings("balanced", [over], str(path), set_keys([over]))
    # the config's samples: the rays the scene decided for its own samples do not follow them
    assert (st.stage1.rays, st.avatar.render.samples) == (4096, 24)
    plain = stage_settings("balanced", [], str(path))
    assert (plain.stage1.rays, plain.avatar.render.samples) == (4096, 40)  # balanced allows no more than its rays
    assert stage_settings("balanced", []).raw == resolve("balanced").raw  # no scene: the preset


def test_stage_two_grows_with_the_room_from_the_configured_length(tmp_path):
    assert stage2_factor(0.1, 0.1) == 1.0  # the preset's room: the configured steps
    assert stage2_factor(0.05, 0.1) == 1.0  # never fewer
    assert stage2_factor(0.286, 0.1) == 2.86  # a dress's room
    assert stage2_factor(0.6, 0.1) == 3.0  # at most 3x
    path = tmp_path / "scene.json"
    path.write_text(json.dumps({"decisions": {"stage2": {"length_factor": 2.86}}}))
    assert scene_settings(path, {"stage2": {"iterations": 300}}, []) == {"stage2": {"iterations": 858}}
    assert scene_settings(path, {"stage2": {"iterations": 300}}, ["stage2.iterations"]) == {}  # the user's wins


@pytest.mark.parametrize("crop, frames", [(512, 130), (512, 400), (540, 400), (1080, 400), (2048, 4000), (64, 1)])
def test_the_training_resolution_is_the_capture_unless_its_frames_overflow_the_budget(crop, frames):
    n = training_resolution(crop, frames)
    fits = lambda m: m * m * BYTES_PER_PIXEL * frames <= FRAME_BUDGET  # noqa: E731
    if fits(crop):
        assert n == crop
    else:  # the largest multiple of 16 that fits
        assert n % 16 == 0 and fits(n) and not fits(n + 16) and n < crop
    assert training_resolution(512, 400) == 512 and training_resolution(1080, 400) == 576
    assert training_resolution(512, 10**9) == 16  # never below 16 pixels


def test_decisions_apply_only_where_the_config_is_silent(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps({"decisions": {"exterior": "no", "capture": "upper", "resolution": 512,
                                              "render": {"max_dist": 0.3, "samples": 40}}}))  # fmt: skip
    auto = {"exterior": "auto", "capture": "auto", "resolution": 128}
    assert scene_settings(path, auto, []) == {"exterior": "no", "capture": "upper", "resolution": 512,
                                              "render": {"max_dist": 0.3, "samples": 40}}  # fmt: skip
    assert scene_settings(path, auto, ["render.samples", "capture", "resolution"]) == {
        "exterior": "no", "render": {"max_dist": 0.3}}  # fmt: skip
    assert scene_settings(path, {"exterior": "yes", "capture": "full"}, []) == {
        "resolution": 512, "render": {"max_dist": 0.3, "samples": 40}}  # fmt: skip
    path.write_text("{}")
    with pytest.raises(Exception, match="not a scene analysis"):
        scene_settings(path, auto, [])


def test_a_tracked_faces_head_weights_reach_the_loss_weights_unless_the_config_sets_them(tmp_path):
    path = tmp_path / "scene.json"
    decisions = {"resolution": 64, "weights": HEAD_WEIGHTS, "semantic": HEAD_SEMANTIC}
    path.write_text(json.dumps({"decisions": decisions}))
    taken = scene_settings(path, {"exterior": "auto"}, [])
    assert taken == {"resolution": 64, "semantic": "perceptual",
                     "weights": {"semantic": 0.015, "skin_inside": 0.001, "face_points": 10.0}}  # fmt: skip
    body = resolve("fast")
    head = resolve("fast", taken)
    assert (head.weights.semantic, head.weights.skin_inside, head.semantic) == (0.015, 0.001, "perceptual")
    assert (body.weights.semantic, body.weights.skin_inside, body.semantic) == (0.0005, 0.01, "idmrf")
    assert (head.weights.face_points, body.weights.face_points) == (10.0, 0.0)  # held to its points: a face only
    assert head.weights.inside == body.weights.inside and head.weights.offset == body.weights.offset
    # the semantic loss and its weight are one decision: a config setting either keeps its own pair
    for own in (["weights.semantic"], ["semantic"]):
        assert scene_settings(path, {}, own) == {
            "resolution": 64,
            "weights": {"skin_inside": 0.001, "face_points": 10.0},
        }
    assert user_decided(["weights.skin_inside", "weights.edge"], 1) == ["weights.skin_inside"]
    # the semantic loss is stage 2's: setting it does not touch stage 1's job
    assert user_decided(["semantic", "stage2.iterations"], 1) == []
    assert user_decided(["semantic", "stage1.rays"], 2) == ["semantic"]


@pytest.mark.slow
def test_a_tracked_face_takes_the_head_weights_and_a_body_does_not(tiny_training, tmp_path):
    t = tiny_training["tight"]
    body = analyze(t["record"], t["init"], t["body"], 0.1, 16, size=32, frames=3)
    assert "weights" not in body["decisions"] and "weights" not in body["evidence"]
    with np.load(t["init"]) as p:  # the same fit with a tracked face: three expression coefficients a frame
        arrays = dict(p)
    arrays["expression"] = np.zeros((len(arrays["poses"]), 3), np.float32)
    face_init = tmp_path / "face_params.npz"
    np.savez(face_init, **arrays)
    face = analyze(t["record"], face_init, t["body"], 0.1, 16, size=32, frames=3)
    assert face["decisions"]["weights"] == HEAD_WEIGHTS and face["decisions"]["semantic"] == "perceptual"
    assert "semantic" not in body["decisions"]
    assert "a tracked face (3 expression coefficients a frame)" in face["evidence"]["weights"]["why"]
    # no face landmarks in this record: no open mouth, the preset's shade, and the evidence says so
    assert "mouth_shade" not in face["decisions"] and face["evidence"]["mouth_shade"]["open_frames"] == 0
    assert "mouth_shade" not in body["evidence"]
    assert {k: v for k, v in face["decisions"].items() if k not in ("weights", "semantic")} == body["decisions"]


@pytest.mark.slow
def test_a_dress_reaches_farther_than_trousers_and_a_wider_silhouette_reaches_farther(tiny_training, tmp_path):
    t, d = tiny_training["tight"], tiny_training["loose"]
    tight = analyze(t["record"], t["init"], t["body"], 0.1, 16, size=64, frames=6)
    dress = analyze(d["record"], d["init"], d["body"], 0.1, 16, size=64, frames=6)
    r_tight, r_dress = tight["evidence"]["reach"]["reach_m"], dress["evidence"]["reach"]["reach_m"]
    assert r_dress > r_tight + 0.03, (r_tight, r_dress)
    assert dress["decisions"]["render"]["max_dist"] >= tight["decisions"]["render"]["max_dist"]
    # stage 2 is as long as the room asks: the dress's longer than the trousers' (the same preset)
    rooms = [s["decisions"]["render"]["max_dist"] for s in (tight, dress)]
    factors = [s["decisions"]["stage2"]["length_factor"] for s in (tight, dress)]
    assert factors == [stage2_factor(r, 0.1) for r in rooms] and factors[1] >= factors[0]
    assert tight["decisions"]["exterior"] == dress["decisions"]["exterior"] == "yes"
    assert tight["decisions"]["capture"] == "full"
    assert "shell" not in tight["decisions"]["render"] and "shell" not in dress["evidence"]  # full bodies: none
    with h5py.File(t["record"], "r") as h5:  # trained at the capture's crop, which fits the budget
        assert tight["decisions"]["resolution"] == h5["images"].shape[1] == 64
    # a training pixel's footprint does not depend on the size the analysis looks at, and sets the samples
    foot = tight["evidence"]["samples"]["pixel_footprint_mm"]
    half = analyze(t["record"], t["init"], t["body"], 0.1, 16, size=32, frames=6)["evidence"]["samples"]
    assert half["pixel_footprint_mm"] == pytest.approx(foot, rel=0.05)
    assert 10 < foot < 60  # a 1.5-m body across most of 64 pixels
    assert tight["decisions"]["render"]["samples"] == room_and_samples(r_tight, 0.1, 16, foot / 1000)[1]
    assert "stage1" not in tight["decisions"]  # no preset's rays given: stage 1 keeps its own
    rays = analyze(t["record"], t["init"], t["body"], 0.1, 16, size=64, frames=6, preset_rays=4096, max_rays=8192)
    samples = rays["decisions"]["render"]["samples"]
    assert rays["decisions"]["stage1"]["rays"] == step_rays(samples, 16, 4096, 8192)
    assert rays["evidence"]["rays"]["samples"] == samples and str(samples) in rays["evidence"]["rays"]["why"]
    # the same capture with every person mask grown by 3 pixels (about 9 cm at this size) reaches farther
    wide = tmp_path / "wide.h5"
    shutil.copy(t["record"], wide)
    import cv2

    with h5py.File(wide, "r+") as h5:
        kernel = np.ones((7, 7), np.uint8)
        h5["person"][...] = np.stack([cv2.dilate(m, kernel) for m in h5["person"][:]])
    grown = analyze(wide, t["init"], t["body"], 0.1, 16, size=64, frames=6)
    assert grown["evidence"]["reach"]["reach_m"] > r_tight + 0.03
    # and with no clothing or hair parsed there is nothing to model beyond the body
    bare = tmp_path / "bare.h5"
    shutil.copy(t["record"], bare)
    with h5py.File(bare, "r+") as h5:
        for m in ("clothing", "hair"):
            if m in h5:
                h5[m][...] = 0
    none = analyze(bare, t["init"], t["body"], 0.1, 16, size=64, frames=6)
    assert none["decisions"]["exterior"] == "no" and "0.0%" in none["evidence"]["exterior"]["why"]
    assert "stage2" not in none["decisions"]


@pytest.mark.slow
def test_training_takes_the_scene_and_says_so(tiny_training, tmp_path, caplog):
    from delta.training.run import run_stage

    t = tiny_training["tight"]
    scene = tmp_path / "scene.json"
    scene.write_text(
        json.dumps({"decisions": {"exterior": "no", "capture": "full", "render": {"max_dist": 0.3, "samples": 12}}})
    )
    tiny = {"resolution": 32, "render": {"samples": 8},
            "stage1": {"iterations": 2, "rays": 64, "checkpoint_every": 2, "preview_every": 0}}  # fmt: skip
    with caplog.at_level("INFO"):
        run_stage(1, t["record"], t["body"], t["init"], str(tmp_path / "s1"), "fast", [tiny], scene=str(scene),
                  user_set=["render.samples"])  # fmt: skip
    settings = json.loads((tmp_path / "s1" / "settings.json").read_text())
    assert settings["nerf"] is False  # the scene found no exterior: no NeRF
    assert settings["settings"]["render"]["max_dist"] == 0.3  # decided by the scene
    assert settings["settings"]["render"]["samples"] == 8  # the config set it: the config wins
    assert "from the scene analysis" in caplog.text


def test_only_the_keys_the_scene_decides_are_passed_to_training():
    set_by_config = ["stage2.lr_final", "render.samples", "render.sil_sigma", "exterior", "stage1.iterations"]
    assert user_decided(set_by_config) == ["exterior", "render.samples"]
    assert user_decided(set_by_config + ["resolution"], 2) == ["exterior", "render.samples", "resolution"]
    assert user_decided([]) == []
    # a stage's job carries only the keys it reads: stage 2's length must not rerun stage 1
    assert user_decided(set_by_config + ["stage2.iterations"], 1) == ["exterior", "render.samples"]
    assert user_decided(set_by_config + ["stage2.iterations"], 2) == ["exterior", "render.samples", "stage2.iterations"]
