"""The workflow on a real one-node SLURM (tests/cluster/run_slurm_test.sh); opt-in, it needs root and ~15 minutes.

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
