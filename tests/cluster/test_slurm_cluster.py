"""The workflow on a real one-node SLURM (tests/cluster/run_slurm_test.sh); opt-in, it needs root and ~15 minutes.
The harness's file comparison is tested without a cluster.

    DELTA_SLURM_TEST=1 pytest tests/cluster
"""

import os
import subprocess
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get("DELTA_SLURM_TEST") != "1", reason="set DELTA_SLURM_TEST=1 (root, Debian, ~15 min)")
def test_tiny_workflow_on_a_one_node_slurm(tmp_path):
    """Outputs equal a local run's; a scancel'ed training job resumes from its checkpoint to the same model."""
    res = subprocess.run(["bash", str(HERE / "run_slurm_test.sh"), str(tmp_path)], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-4000:]
    assert "equal outputs" in res.stdout and "equal a run never killed" in res.stdout


def test_comparison_is_bitwise_ignores_wall_clock_and_says_what_differs(tmp_path):
    """The harness's comparison (no cluster needed): NaN equals NaN, `seconds` columns/keys are left out,
    a last-bit difference in a tensor is reported with its key and size."""
    import sys

    import torch

    sys.path.insert(0, str(HERE))
    from slurm_e2e import file_differences

    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    w = torch.tensor([1.0, float("nan"), 3.0])
    torch.save({"model": {"w": w}, "rows": [{"step": 1, "seconds": 0.5}]}, a / "m.pt")
    torch.save({"model": {"w": w.clone()}, "rows": [{"step": 1, "seconds": 0.7}]}, b / "m.pt")
    (a / "l.csv").write_text("step,loss,seconds\n1,0.25,1.5\n")
    (b / "l.csv").write_text("step,loss,seconds\n1,0.25,2.5\n")
    assert file_differences(a / "m.pt", b / "m.pt") == [] and file_differences(a / "l.csv", b / "l.csv") == []
    w2 = w.clone()
    w2[2] = torch.nextafter(w2[2], torch.tensor(4.0))  # one ulp
    torch.save({"model": {"w": w2}, "rows": []}, b / "m.pt")
    diff = file_differences(a / "m.pt", b / "m.pt")
    assert any(d.startswith("/model/w: 1/3 values differ") for d in diff) and any("/rows" in d for d in diff)
    (b / "l.csv").write_text("step,loss,seconds\n1,0.2500001,1.5\n")
    assert file_differences(a / "l.csv", b / "l.csv") == ["[0]/loss: '0.25' vs '0.2500001'"]
