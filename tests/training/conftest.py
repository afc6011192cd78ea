"""Tiny training inputs: frame records of the tiny synthetic captures, initialised from their ground truth."""

import numpy as np
import pytest

from delta.data.record import FrameRecord
from delta.data.sources import synthetic_source
from delta.io import save_npz
from delta.preprocess.frames import prepare


def init_from_gt(capture, record_path, out_path):
    """The ground-truth body parameters of the record's frames, written as an init fit would."""
    gt = np.load(capture / "gt" / "params.npz")
    with FrameRecord(record_path) as rec:
        ids = rec.h5["frame_ids"][:]
        cam = {"camera_model": np.array(rec.h5.attrs["camera_model"])}
        if rec.h5.attrs["camera_model"] == "orthographic":
            cam.update(ortho_scale=rec.h5["ortho_scale"][:], ortho_trans=rec.h5["ortho_trans"][:])
    save_npz(out_path, betas=gt["betas"], poses=gt["poses"][ids], transl=gt["transl"][ids], frame_ids=ids, **cam)


@pytest.fixture(scope="session")
def tiny_training(tmp_path_factory, tiny_captures, anny_files):
    """{subject: {"record", "init", "body"}} for the tiny pinhole (tight) and orthographic (loose) subjects."""
    root = tmp_path_factory.mktemp("training")
    out = {}
    for name in ("tight", "loose"):
        record = root / name / "frames.h5"
        prepare(synthetic_source(tiny_captures / name, name), record, size=64)
        init_from_gt(tiny_captures / name, record, root / name / "init.npz")
        out[name] = {"record": str(record), "init": str(root / name / "init.npz"), "body": anny_files["body"]}
    return out
