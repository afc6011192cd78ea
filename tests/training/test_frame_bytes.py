"""Training frames held as bytes: what is read back is the float frame to half a byte step, computed
here independently from the record; totals match float sums; the memory is a byte a value."""

import h5py
import numpy as np
import pytest
import torch

from delta.data.frames import ByteFrames, claim_fringe, load_frames

STEP = 1.0 / 255.0


def test_quantise_rounds_to_half_a_step_and_clips():
    v = np.concatenate([np.linspace(0.0, 1.0, 10_001), [0.0, 1.0, -0.2, 1.3, 0.5 * STEP, 1.5 * STEP]]).astype(
        np.float32
    )
    held = ByteFrames(torch.from_numpy(ByteFrames.quantise(v)))
    back = held[:].numpy()
    inside = (v >= 0) & (v <= 1)
    assert np.abs(back[inside] - v[inside]).max() <= 0.5 * STEP + 1e-7
    assert back[-4] == 0.0 and back[-3] == 1.0  # out of range: clipped
    assert back[0] == 0.0 and back[10_000] == 1.0  # the ends are exact
    assert held.total(slice(None)) == pytest.approx(float(held.bytes.double().sum()) / 255.0, rel=1e-12)
    with pytest.raises(TypeError, match="uint8"):
        ByteFrames(torch.zeros(3))


@pytest.mark.parametrize("background", [(1.0, 1.0, 1.0), (0.0, 0.5, 1.0)])
def test_loaded_frames_are_the_float_frames_to_half_a_step(tiny_training, background):
    record = tiny_training["loose"]["record"]
    data = load_frames(record, 64, background, hair=True)
    for field in (data.images, data.person, data.exterior, data.interior, data.hair):
        assert field.bytes.dtype == torch.uint8 and field.bytes.element_size() == 1
    bg = np.asarray(background, np.float32)
    with h5py.File(record, "r") as h5:
        assert h5["images"].shape[1] == 64  # the record's own size: no resampling in this check
        masks = [m for m in ("clothing", "hair") if m in h5]
        for f in (0, len(data.split) // 2, len(data.split) - 1):
            a = h5["person"][f].astype(np.float32) / 255.0
            img = h5["images"][f].astype(np.float32) / 255.0 * a[..., None] + bg * (1 - a[..., None])
            # the parts with the person's unlabelled fringe claimed (tests/training/test_fringe.py checks that)
            parts = claim_fringe(h5["person"][f], {m: h5[m][f] > 0 for m in masks + ["skin"]})
            ext = np.minimum(np.any([parts[m] for m in masks], 0).astype(np.float32), a)
            hair = np.minimum(parts["hair"].astype(np.float32), a)
            for got, want in ((data.images[f], img), (data.person[f], a), (data.exterior[f], ext),
                              (data.interior[f], np.clip(a - ext, 0, 1)), (data.hair[f], hair)):  # fmt: skip
                assert got.dtype == torch.float32
                assert np.abs(got.numpy() - want).max() <= 0.5 * STEP + 1e-6
    # the skin colour: the visible body's mean colour over the training frames, from the floats
    w = data.interior[data.train].double()
    skin = (data.images[data.train].double() * w[..., None]).sum((0, 1, 2)) / w.sum()
    assert torch.allclose(data.skin_color.double(), skin, atol=1e-6)
    assert data.person.total(data.train) == pytest.approx(float(data.person[data.train].double().sum()), rel=1e-6)
