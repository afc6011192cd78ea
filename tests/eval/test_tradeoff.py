"""The trade-off table: time to a PSNR, the Pareto front, speed-ups against the reference, throughput."""

import json
import math

import numpy as np
import pandas as pd
import pytest
import torch

from delta.eval.tradeoff import curve_time_to, front_at, pareto_front, place_labels, time_to_psnr, tradeoff
from delta.eval.tradeoff import psnr_gain as tradeoff_gain
from delta.training.profile import matmul_peak, profile_steps


def losses(seconds_per_step, psnr_per_step, steps=200, start=10.0):
    s = np.arange(1, steps + 1)
    return pd.DataFrame({"step": s, "psnr": start + psnr_per_step * s, "seconds": seconds_per_step * s})


def test_time_to_psnr_reads_the_smoothed_curve():
    df = losses(0.5, 0.1)  # PSNR 10 + 0.1 s; the 25-step average lags by 1.2 dB
    t = time_to_psnr(df, 20.0)
    first = int(np.argmax((df["psnr"].rolling(25, min_periods=1).mean() >= 20.0).to_numpy()))
    assert t == pytest.approx(df["seconds"].iloc[first])
    assert math.isnan(time_to_psnr(df, 99.0))


def test_a_nerf_only_warmup_is_timed_but_not_scored():
    """Warm-up rows (the NeRF alone, another render) count towards the time, never towards the PSNR."""
    df = losses(0.5, 0.1)
    warm = df.assign(warmup=(df["step"] <= 50).astype(float))
    warm.loc[warm["warmup"] == 1, "psnr"] = 40.0  # a warm-up PSNR above every target: must be ignored
    hybrid = df[df["step"] > 50]
    assert time_to_psnr(warm, 20.0) == pytest.approx(time_to_psnr(hybrid, 20.0))
    assert time_to_psnr(warm, 20.0) > 50 * 0.5  # from the stage's start
    assert tradeoff_gain(warm) == pytest.approx(tradeoff_gain(hybrid))
    assert tradeoff_gain(warm) == pytest.approx(float(df["psnr"].iloc[-25:].mean() - df["psnr"].iloc[50:75].mean()))


def test_pareto_front():
    cost = np.array([1.0, 2.0, 3.0, 2.0, np.nan])
    gain = np.array([20.0, 25.0, 24.0, 22.0, 30.0])
    # 3 is slower and worse than 2; 4 costs as much as 2 and is worse; nan is never on the front
    assert pareto_front(cost, gain).tolist() == [True, True, False, False, False]


def test_time_to_a_held_out_psnr_between_snapshots():
    """Linear between the two snapshots around the first crossing; a dip after it does not move it."""
    seconds = np.array([100.0, 200.0, 400.0, 800.0])
    psnr = np.array([24.0, 26.0, 27.0, 26.5])
    assert curve_time_to(seconds, psnr, 26.5) == pytest.approx(300.0)  # halfway from 26 to 27 dB
    assert curve_time_to(seconds, psnr, 26.0) == pytest.approx(200.0)  # on a snapshot
    assert curve_time_to(seconds, psnr, 23.0) == pytest.approx(100.0)  # before the first: its time
    assert math.isnan(curve_time_to(seconds, psnr, 27.5))  # never


def test_the_front_at_a_time_is_the_best_of_what_was_trained_as_long():
    seconds = np.array([100.0, 300.0, 200.0, 50.0])
    psnr = np.array([25.0, 27.0, 26.0, np.nan])
    assert front_at(seconds, psnr, 250.0) == 26.0
    assert front_at(seconds, psnr, 300.0) == 27.0
    assert math.isnan(front_at(seconds, psnr, 60.0))  # only an unscored point so soon


def test_plot_labels_do_not_overlap():
    # five labels on one point and one far away: the lone one stays at the default offset,
    # the five are moved a line at a time until no two boxes meet
    anchors = np.array([[100.0, 100.0]] * 5 + [[400.0, 10.0]])
    widths, height = np.full(6, 50.0), 8.0
    off = place_labels(anchors, widths, height, gap=3.0)
    assert off[5].tolist() == [3.0, 3.0] and off[0].tolist() == [3.0, 3.0]
    boxes = [(a[0] + o[0], a[1] + o[1], a[0] + o[0] + w, a[1] + o[1] + height) for a, o, w in zip(anchors, off, widths)]
    for i in range(6):
        for j in range(i):
            a, b = boxes[i], boxes[j]
            assert not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]), (i, j)
    assert sorted(off[:5, 1].tolist()) == [3.0 - 18, 3.0 - 9, 3.0, 3.0 + 9, 3.0 + 18]  # a line is height + 1


def write_variant(root, name, sec_per_step, psnr_per_step, held_out, train_s, flops, eval_resolution=None, start=10.0):
    d = root / name
    d.mkdir()
    losses(sec_per_step, psnr_per_step, start=start).to_csv(d / "losses.csv", index=False)
    (d / "bench.tsv").write_text(f"s\tmax_rss\n{train_s}\t900\n")
    summary = {"scores": {"test_view": {"unrefined": {"psnr": held_out, "ssim": 0.9}}}}
    if eval_resolution:  # summaries written before scoring at a common resolution have no 'resolution'
        summary["settings"] = {"resolution": eval_resolution}
    (d / "summary.json").write_text(json.dumps(summary))
    (d / "profile.json").write_text(json.dumps({"flops": flops, "seconds": 0.5, "samples": 1000.0, "rays": 64,
                                                "preset": "fast", "settings": {"resolution": 64, "render": {"samples": 8},
                                                "nerf": {"encoding": "grid"}, "stage1": {"rays": 64}}}))  # fmt: skip
    return {"summary": str(d / "summary.json"), "profile": str(d / "profile.json"), "losses1": str(d / "losses.csv"),
            "bench1": str(d / "bench.tsv")}  # fmt: skip


def test_speedup_against_the_reference(tmp_path):
    # the reference climbs 0.05 dB/step at 2 s/step; "fast" 0.1 dB/step at 0.2 s/step
    manifest = {"s": {"reference": write_variant(tmp_path, "ref", 2.0, 0.05, 21.0, 400.0, 1e9),
                      "fast": write_variant(tmp_path, "fast", 0.2, 0.1, 23.0, 40.0, 1e8, eval_resolution=128)}}  # fmt: skip
    (tmp_path / "peak.json").write_text(json.dumps({"flop_per_s": 1e10}))
    df = tradeoff(manifest, tmp_path / "peak.json", "reference", tmp_path / "t.csv", tmp_path / "t.png").set_index(
        "variant"
    )
    # trained at 64², scored at its own size (no 'resolution' in the summary) or at a common 128²
    assert df.loc["reference", "eval_resolution"] == 64 and df.loc["fast", "eval_resolution"] == 128
    target = df.loc["reference", "reference_psnr"]
    ref = losses(2.0, 0.05)
    t_ref, t_fast = time_to_psnr(ref, target), time_to_psnr(losses(0.2, 0.1), target)
    assert df.loc["fast", "speedup_vs_reference"] == pytest.approx(t_ref / t_fast)
    assert df.loc["fast", "speedup_vs_reference"] > 10
    assert df.loc["reference", "speedup_vs_reference"] == pytest.approx(1.0)
    assert df.loc["fast", "pareto"] and not df.loc["reference", "pareto"]  # slower and worse
    assert df.loc["fast", "flop_per_s"] == pytest.approx(2e8) and df.loc["fast", "peak_fraction"] == pytest.approx(0.02)
    assert df.loc["fast", "samples_per_s"] == pytest.approx(2000.0)
    assert df.loc["fast", "nerf_backend"] == "grid" and df.loc["fast", "held_out_psnr"] == 23.0
    assert (tmp_path / "t.png").stat().st_size > 1000 and (tmp_path / "t.csv").is_file()


def test_cli_takes_a_manifest_longer_than_path_max(tmp_path, capsys):
    # a whole sweep's manifest (~7 kB inline) is longer than PATH_MAX: it must not be tried as a path
    from delta.cli import main

    variants = {"reference": write_variant(tmp_path, "ref", 2.0, 0.05, 21.0, 400.0, 1e9)}
    for i in range(40):
        variants[f"fast_{i:02d}_" + "x" * 40] = write_variant(tmp_path, f"fast{i}", 0.2, 0.1, 23.0, 40.0, 1e8)
    manifest = json.dumps({"s": variants})
    assert len(manifest) > 4096
    (tmp_path / "peak.json").write_text(json.dumps({"flop_per_s": 1e10}))
    common = ["--peak", str(tmp_path / "peak.json"), "--reference", "reference", "--plot", str(tmp_path / "t.png")]
    assert main(["tradeoff", "--manifest", manifest, "--out", str(tmp_path / "inline.csv"), *common]) == 0
    (tmp_path / "manifest.json").write_text(manifest)
    assert (
        main(["tradeoff", "--manifest", str(tmp_path / "manifest.json"), "--out", str(tmp_path / "file.csv"), *common])
        == 0
    )
    inline, from_file = pd.read_csv(tmp_path / "inline.csv"), pd.read_csv(tmp_path / "file.csv")
    assert len(inline) == 41 and inline.equals(from_file)
    # bad input names the argument and what is wrong, with the CLI's error code
    assert main(["tradeoff", "--manifest", "{not json", "--out", str(tmp_path / "x.csv"), *common]) == 2
    assert "--manifest: not valid JSON" in capsys.readouterr().err
    assert (
        main(["tradeoff", "--manifest", str(tmp_path / "missing.json"), "--out", str(tmp_path / "x.csv"), *common]) == 2
    )
    assert "missing.json is neither inline JSON nor an existing JSON file" in capsys.readouterr().err
    assert not (tmp_path / "x.csv").exists()


def test_no_speedup_against_a_reference_that_did_not_learn(tmp_path):
    """A flat reference curve is 'reached' at every run's first step: the ratio would be the step times'."""
    manifest = {"s": {"reference": write_variant(tmp_path, "ref", 2.0, 0.0, 14.0, 400.0, 1e9),
                      "fast": write_variant(tmp_path, "fast", 0.2, 0.1, 23.0, 40.0, 1e8)}}  # fmt: skip
    (tmp_path / "peak.json").write_text(json.dumps({"flop_per_s": 1e10}))
    df = tradeoff(manifest, tmp_path / "peak.json", "reference", tmp_path / "t.csv", tmp_path / "t.png").set_index(
        "variant"
    )
    assert df["speedup_vs_reference"].isna().all() and (df["reference_gain_db"] == 0.0).all()
    # the climbing reference of the test above gained 0.05 dB a step: final (25-step mean) minus the first 25
    climbing = losses(2.0, 0.05)
    gain = climbing["psnr"].iloc[-25:].mean() - climbing["psnr"].iloc[:25].mean()
    assert tradeoff_gain(climbing) == pytest.approx(gain) and gain > 0.5


def test_no_speedup_for_a_run_that_starts_past_a_short_reference(tmp_path):
    """A reference cut short ends at 12.4 dB; a run whose first 25 steps already average more 'reaches'
    it at its first step — the ratio would set the reference's whole run against one step."""
    manifest = {"s": {"reference": write_variant(tmp_path, "ref", 2.0, 0.0125, 14.0, 100.0, 1e9, start=10.0),
                      "fast": write_variant(tmp_path, "fast", 0.2, 0.01, 23.0, 40.0, 1e8, start=15.0),
                      "slow_start": write_variant(tmp_path, "slow", 0.2, 0.1, 20.0, 40.0, 1e8, start=5.0)}}  # fmt: skip
    (tmp_path / "peak.json").write_text(json.dumps({"flop_per_s": 1e10}))
    df = tradeoff(manifest, tmp_path / "peak.json", "reference", tmp_path / "t.csv", tmp_path / "t.png").set_index(
        "variant"
    )
    target = df.loc["reference", "reference_psnr"]
    assert (
        df.loc["fast", "train_psnr_start"] == pytest.approx(15.0 + 0.01 * 13)
        and df.loc["fast", "train_psnr_start"] > target
    )
    assert math.isnan(df.loc["fast", "speedup_vs_reference"])
    assert df.loc["fast", "time_to_reference_psnr_s"] == pytest.approx(0.2)  # measured all the same: its first step
    t_ref, t_slow = time_to_psnr(losses(2.0, 0.0125), target), time_to_psnr(losses(0.2, 0.1, start=5.0), target)
    assert df.loc["slow_start", "speedup_vs_reference"] == pytest.approx(t_ref / t_slow)
    assert df.loc["reference", "speedup_vs_reference"] == pytest.approx(1.0)


def test_a_resumed_stage_is_timed_by_the_training_clock(tmp_path):
    """A job resumed from a checkpoint: its benchmark timed the last invocation only (100 s of 400)."""
    manifest = {"s": {"reference": write_variant(tmp_path, "ref", 2.0, 0.05, 21.0, 100.0, 1e9),
                      "fast": write_variant(tmp_path, "fast", 0.2, 0.1, 23.0, 45.0, 1e8)}}  # fmt: skip
    (tmp_path / "peak.json").write_text(json.dumps({"flop_per_s": 1e10}))
    df = tradeoff(manifest, tmp_path / "peak.json", "reference", tmp_path / "t.csv", tmp_path / "t.png").set_index(
        "variant"
    )
    # the reference's clock ends at 200 steps x 2 s; fast's benchmark (45 s, set-up included) outlasts its 40-s clock
    assert df.loc["reference", "stage1_s"] == 400.0 and df.loc["reference", "stage1_resumed"]
    assert df.loc["fast", "stage1_s"] == 45.0 and not df.loc["fast", "stage1_resumed"]
    assert df.loc["reference", "train_s"] == 400.0 and df.loc["fast", "pareto"] and not df.loc["reference", "pareto"]


def test_matmul_peak_is_a_rate():
    peak = matmul_peak(256, repeats=3)
    assert 1e8 < peak < 1e14


@pytest.mark.slow
def test_profile_of_a_tiny_training_step(tiny_trained):
    from delta.training.run import load_trained

    t = tiny_trained["tight"]
    tr = load_trained(t["model"], t["record"], t["body"])
    before = {k: v.clone() for k, v in tr.model.state_dict().items()}
    p = profile_steps(tr.model, tr.data, tr.settings, 1, steps=2)
    # the NeRF and vertex-field MLPs alone: at least 2·(in·out) FLOPs per sample and layer, forward
    assert p.flops > 2 * p.samples * 64 and p.seconds > 0 and p.samples > 0 and p.rays == 128
    after = tr.model.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)  # profiling never changes the model
