"""Atomic outputs: a failure leaves neither a partial file nor a temporary one."""

import numpy as np
import pytest

from delta.io import atomic_path, save_json, save_npz


def test_atomic_path_commits_on_success(tmp_path):
    target = tmp_path / "sub" / "out.txt"
    with atomic_path(target) as tmp:
        assert tmp.suffix == ".txt" and tmp.parent == target.parent
        tmp.write_text("done")
        assert not target.exists()
    assert target.read_text() == "done"
    assert list(target.parent.iterdir()) == [target]


def test_atomic_path_keeps_old_file_on_failure(tmp_path):
    target = tmp_path / "out.npz"
    save_npz(target, a=np.arange(3))
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("interrupted")
    with np.load(target) as data:
        np.testing.assert_array_equal(data["a"], np.arange(3))
    assert list(tmp_path.iterdir()) == [target]


def test_save_json_round_trip(tmp_path):
    save_json(tmp_path / "x.json", {"b": 1, "a": [1.5]})
    assert (tmp_path / "x.json").read_text().startswith('{\n  "a"')


def test_save_npz_is_byte_identical_and_loadable(tmp_path):
    arrays = dict(a=np.arange(5.0), names=np.array(["x", "yz"]))
    save_npz(tmp_path / "1.npz", **arrays)
    import time

    time.sleep(1.1)  # np.savez would stamp a different time
    save_npz(tmp_path / "2.npz", **arrays)
    assert (tmp_path / "1.npz").read_bytes() == (tmp_path / "2.npz").read_bytes()
    with np.load(tmp_path / "1.npz", allow_pickle=False) as data:
        np.testing.assert_array_equal(data["a"], arrays["a"])
        assert data["names"].tolist() == ["x", "yz"]
