"""Anti-aliasing: jittered training rays and supersampled renders match area-averaged frames."""

import numpy as np
import pytest
import torch

from delta import DeltaError
from delta.data.frames import EDGE_PX, sample_rays
from delta.metrics import outline_band
from delta.models.image import EDGE, busy_pixels, pixel_grid, render_image
from delta.training.presets import resolve


def test_pixel_grid_centres_and_subpixels():
    c = pixel_grid(3)
    assert c.shape == (9, 2)
    torch.testing.assert_close(c[:4], torch.tensor([[0.5, 0.5], [1.5, 0.5], [2.5, 0.5], [0.5, 1.5]]))
    s = pixel_grid(2, supersample=2)
    assert s.shape == (16, 2)
    # pixel (row 0, col 1): its four sub-pixel centres, then pixel (row 0, col 0) averages to its centre
    torch.testing.assert_close(s[4:8], torch.tensor([[1.25, 0.25], [1.75, 0.25], [1.25, 0.75], [1.75, 0.75]]))
    torch.testing.assert_close(s.reshape(4, 4, 2).mean(1), pixel_grid(2))
    # the sub-pixel average of an edge at u = 0.6 is the pixel's covered area to within 1/(2s)
    for k in (1, 2, 4, 8):
        cover = (pixel_grid(1, supersample=k)[:, 0] < 0.6).float().mean()
        assert abs(float(cover) - 0.6) <= 0.5 / k + 1e-6
    with pytest.raises(ValueError, match="supersample"):
        pixel_grid(2, supersample=0)


class _Frames:
    """Just what sample_rays reads: images indexed (frame, row, col) with a distinct value per pixel."""

    def __init__(self, n=8):
        v = torch.arange(n * n, dtype=torch.float32).reshape(1, n, n)
        self.images = v[..., None].expand(1, n, n, 3).clone()
        self.person = self.exterior = self.interior = v.clone()
        self.boxes = torch.tensor([[2, 6, 1, 7]])
        self.resolution = n
        self.hair = None  # no hair mask loaded (an exterior of one NeRF)


def test_jittered_rays_pass_through_the_pixel_whose_target_they_carry():
    data = _Frames()
    b = sample_rays(data, 0, 4000, torch.Generator().manual_seed(0), patch=3)
    u, v = b.pixels[:, 0], b.pixels[:, 1]
    row, col = v.floor().long(), u.floor().long()
    assert torch.equal(b.rgb[:, 0], data.images[0, row, col, 0])  # the ray lies inside its target pixel
    frac = b.pixels[9:] - b.pixels[9:].floor()
    assert 0.45 < float(frac.mean()) < 0.55 and float(frac.std()) > 0.25  # uniform in the pixel, not centred
    assert torch.equal(b.pixels[:9] - b.pixels[:9].floor(), torch.full((9, 2), 0.5))  # the patch stays regular
    assert (row >= 2).all() and (row < 6).all() and (col >= 1).all() and (col < 7).all()
    centred = sample_rays(data, 0, 50, torch.Generator().manual_seed(0), jitter=False)
    assert torch.equal(centred.pixels - centred.pixels.floor(), torch.full((50, 2), 0.5))


def test_a_crop_draws_rays_from_the_central_part_of_the_person_box():
    data = _Frames(n=20)
    data.boxes = torch.tensor([[2, 18, 4, 12]])  # rows 2..17, cols 4..11
    b = sample_rays(data, 0, 4000, torch.Generator().manual_seed(0), crop=0.5)
    row, col = b.pixels[:, 1].floor().long(), b.pixels[:, 0].floor().long()
    assert int(row.min()) == 6 and int(row.max()) == 13  # the middle 8 of 16 rows
    assert int(col.min()) == 6 and int(col.max()) == 9  # the middle 4 of 8 columns
    one = sample_rays(data, 0, 5, torch.Generator().manual_seed(0), crop=1e-6)
    assert (one.pixels[:, 1].floor() == 10).all() and (one.pixels[:, 0].floor() == 8).all()  # at least a pixel
    full = sample_rays(data, 0, 50, torch.Generator().manual_seed(3), crop=1.0)
    same = sample_rays(data, 0, 50, torch.Generator().manual_seed(3))
    assert torch.equal(full.pixels, same.pixels)


def test_edge_rays_come_from_the_outline_and_leave_the_other_draws_alone():
    data = _Frames(n=20)
    data.boxes = torch.tensor([[0, 20, 0, 20]])
    data.person = torch.zeros(1, 20, 20)
    data.person[0, 6:14, 5:12] = 1.0
    plain = sample_rays(data, 0, 400, torch.Generator().manual_seed(4), patch=3)
    edged = sample_rays(data, 0, 400, torch.Generator().manual_seed(4), patch=3, edge=0.25)
    band = {tuple(p) for p in torch.nonzero(outline_band(data.person[0] > 0.5, EDGE_PX)).tolist()}
    rows, cols = edged.pixels[:, 1].floor().long(), edged.pixels[:, 0].floor().long()
    assert all((int(r), int(c)) in band for r, c in zip(rows[9 : 9 + 100], cols[9 : 9 + 100]))
    # the patch and the rest of the random rays are those of a step without edge rays
    assert torch.equal(edged.pixels[:9], plain.pixels[:9])
    assert torch.equal(edged.pixels[109:].floor(), plain.pixels[109:].floor())
    assert torch.equal(edged.rgb[:, 0], data.images[0, rows, cols, 0])  # each ray carries its own pixel
    assert torch.equal(sample_rays(data, 0, 50, torch.Generator().manual_seed(2), edge=0.0).pixels,
                       sample_rays(data, 0, 50, torch.Generator().manual_seed(2)).pixels)  # fmt: skip
    assert resolve("fast", {"stage2": {"edge_rays": 0.25}}).stage2.edge_rays == 0.25
    assert resolve("fast", {}).stage1.edge_rays == resolve("balanced", {}).stage2.edge_rays == 0.0  # off by default
    with pytest.raises(DeltaError, match="stage2.edge_rays"):
        resolve("fast", {"stage2": {"edge_rays": 1.5}})


@pytest.mark.slow
def test_supersampled_silhouette_is_fractional_only_at_the_edge(tiny_trained):
    from delta.training.run import load_trained

    t = tiny_trained["tight"]
    model = load_trained(t["model"], t["record"], t["body"]).model
    one = render_image(model, 0)["silhouette"]
    four = render_image(model, 0, supersample=2)["silhouette"]
    assert set(np.unique(one.numpy())) <= {0.0, 1.0}
    levels = np.unique(four.numpy())
    assert set(np.round(levels * 4, 5)) <= {0, 1, 2, 3, 4} and len(levels) > 2  # coverage in quarters
    frac = (four > 0) & (four < 1)
    inner = (one == 1) & ~frac
    # fractional pixels border the silhouette: each has a pixel with no coverage within two steps (one
    # step at an outer edge; two where a sub-pixel gap, e.g. between the legs, runs past a pixel centre)
    pad = torch.nn.functional.pad
    near = lambda m: pad(m[None, None].float(), (2, 2, 2, 2)).unfold(2, 5, 1).unfold(3, 5, 1).amax((-1, -2))[0, 0] > 0  # noqa: E731
    assert (near((four == 0) | (one == 0)) | ~frac).all() and inner.any()
    assert frac.sum() < 0.5 * (four > 0).sum()  # the edge, not the body


def test_busy_pixels_are_those_beside_a_change_larger_than_the_edge():
    img = torch.zeros(6, 7)
    img[:, 4:] = 1.0  # a vertical edge between columns 3 and 4
    img[0, 0] = 0.5 * EDGE  # a change below the threshold
    mask = torch.zeros(6, 7)
    mask[5, 1] = 1.0  # a single pixel in another channel
    busy = busy_pixels({"rgb": img.reshape(-1, 1).expand(-1, 3), "mask": mask.reshape(-1)}, 6, 7, EDGE).view(6, 7)
    expected = torch.zeros(6, 7, dtype=torch.bool)
    expected[:, 3:5] = True
    expected[4:, 0:3] = True  # the single pixel and its 8 neighbours
    assert torch.equal(busy, expected)
    flat = busy_pixels({"rgb": torch.full((42, 3), 0.3)}, 6, 7, 0.0)
    assert not flat.any()


@pytest.mark.slow
def test_supersampling_where_the_image_changes_is_supersampling_everywhere_to_second_order(tiny_trained):
    """Busy pixels get exactly the s² rays' average; the others their centre ray, which differs from the
    average by far less than the images' own error."""
    from delta.training.run import load_trained

    t = tiny_trained["tight"]
    model = load_trained(t["model"], t["record"], t["body"]).model
    centre = render_image(model, 0, soft_silhouette=False)
    full = render_image(model, 0, supersample=2, soft_silhouette=False, edge=None)
    adaptive = render_image(model, 0, supersample=2, soft_silhouette=False)
    n = model.resolution
    busy = busy_pixels({k: v.reshape(n * n, -1) for k, v in centre.items()}, n, n, EDGE).view(n, n)
    assert 0 < int(busy.sum()) < 0.5 * n * n
    for k in full:
        torch.testing.assert_close(adaptive[k][busy], full[k][busy], atol=1e-5, rtol=0)
        torch.testing.assert_close(adaptive[k][~busy], centre[k][~busy], atol=1e-5, rtol=0)
    mse = float(((adaptive["rgb"] - full["rgb"]) ** 2).mean())
    assert mse < 1e-4  # above 40 dB against every pixel supersampled
    assert float((adaptive["rgb"] - centre["rgb"]).abs().amax()) > 0.1  # the busy pixels did change
