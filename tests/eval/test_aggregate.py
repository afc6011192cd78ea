"""The per-dataset table and the loss plot."""

import json

import cv2
import numpy as np
import pandas as pd
import pytest

from delta import DeltaError
from delta.eval.aggregate import aggregate
from delta.eval.plots import plot_losses, smooth


def write_summary(path, psnr, refined_psnr, body):
    path.write_text(
        json.dumps(
            {
                "preset": "fast",
                "stage": 2,
                "settings": {"refine_steps": 5},
                "seconds": 12.0,
                "train_body_err_mm": body,
                "geometry": {"clothing_chamfer_mm": body / 10, "clothing_p2s_mm": body / 20, "clothing_frames": 2},
                "scores": {
                    "test_view": {
                        "unrefined": {"psnr": psnr, "ssim": 0.9, "frames": 2},
                        "refined": {"psnr": refined_psnr, "ssim": None, "frames": 2},
                    }
                },
            }
        )
    )


def write_bench(path, seconds, rss):
    path.write_text("s\th:m:s\tmax_rss\tmax_vms\n" + f"{seconds}\t0:00:01\t{rss}\t1.0\n")


def test_one_row_per_subject_and_a_mean_row(tmp_path):
    write_summary(tmp_path / "a.json", 20.0, 22.0, 50.0)
    write_summary(tmp_path / "b.json", 24.0, 25.0, 70.0)
    (tmp_path / "ea.json").write_text(
        json.dumps(
            {
                "lineup": {"body_iou": 0.9},
                "clothing": {"faces": 100, "name": "x"},
                "settings": {"grid": 8},
                "seconds": {"total": 3.0},
            }
        )
    )
    (tmp_path / "eb.json").write_text(
        json.dumps(
            {
                "lineup": {"body_iou": 0.8},
                "clothing": {"faces": 300, "name": "y"},
                "settings": {"grid": 8},
                "seconds": {"total": 5.0},
            }
        )
    )
    for s, t in (("a", 10), ("b", 30)):
        write_bench(tmp_path / f"{s}1.tsv", t, 1000)
        write_bench(tmp_path / f"{s}2.tsv", t / 2, 2000)
    bench = [f"{s}/stage{k}={tmp_path / f'{s}{k}.tsv'}" for s in "ab" for k in (1, 2)]
    df = aggregate("syn", ["a", "b"], [str(tmp_path / "a.json"), str(tmp_path / "b.json")],
                   [str(tmp_path / "ea.json"), str(tmp_path / "eb.json")], bench, tmp_path / "m.csv")  # fmt: skip
    table = pd.read_csv(tmp_path / "m.csv")
    assert list(table["subject"]) == ["a", "b", "mean"]
    mean = table.set_index("subject").loc["mean"]
    assert mean["test_view_psnr"] == pytest.approx(22.0)
    assert mean["test_view_psnr_refined"] == pytest.approx(23.5)
    assert mean["stage1_s"] == pytest.approx(20.0) and mean["stage2_s"] == pytest.approx(10.0)
    assert mean["export_lineup_body_iou"] == pytest.approx(0.85)
    assert mean["train_body_err_mm"] == pytest.approx(60.0) and mean["clothing_chamfer_mm"] == pytest.approx(6.0)
    assert mean["clothing_p2s_mm"] == pytest.approx(3.0)
    assert mean["preset"] == "fast" and int(mean["stage"]) == 2
    assert np.isnan(table["test_view_ssim_refined"]).all()  # None in a summary: no value
    assert mean["export_clothing_faces"] == pytest.approx(200) and mean["export_s"] == pytest.approx(4.0)
    assert "export_clothing_name" not in table.columns  # only numbers travel
    assert "export_settings_grid" not in table.columns  # the export's settings stay in its json
    assert len(df) == 3


def test_bad_benchmark_entries_are_named(tmp_path):
    write_summary(tmp_path / "a.json", 20.0, 22.0, 50.0)
    with pytest.raises(DeltaError, match="SUBJECT/RULE=PATH"):
        aggregate("syn", ["a"], [str(tmp_path / "a.json")], [], ["c/stage1=x.tsv"], tmp_path / "m.csv")
    (tmp_path / "bad.tsv").write_text("nothing here\n")
    with pytest.raises(DeltaError, match="bad.tsv"):
        aggregate(
            "syn", ["a"], [str(tmp_path / "a.json")], [], [f"a/stage1={tmp_path / 'bad.tsv'}"], tmp_path / "m.csv"
        )
    assert not (tmp_path / "m.csv").exists()


def test_loss_plot(tmp_path):
    steps = np.arange(1, 101)
    pd.DataFrame({"step": steps, "loss": 1.0 / steps, "psnr": 15 + np.log(steps), "pixel": 0.5 / steps,
                  "edge": np.zeros(100)}).to_csv(tmp_path / "losses.csv", index=False)  # fmt: skip
    plot_losses(tmp_path / "losses.csv", tmp_path / "l.png", "t")
    img = cv2.imread(str(tmp_path / "l.png"))
    assert img is not None and img.shape[0] > 200 and img.shape[1] > 400
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(DeltaError, match="empty.csv"):
        plot_losses(tmp_path / "empty.csv", tmp_path / "e.png")


def test_moving_average():
    np.testing.assert_allclose(smooth(np.array([1.0, 3.0, 5.0, 7.0]), 2), [1.0, 2.0, 4.0, 6.0])
