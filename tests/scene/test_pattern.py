"""The exterior's pattern against a colour grid's cells: analytic images, the decision, and what training takes."""

import json
import math
import shutil

import h5py
import numpy as np
import pytest

from delta.scene.pattern import CELL_PIXELS, MAX_DB, PATTERN_DB, colour_cell, exterior_ceilings, grid_residual
from delta.scene.settings import scene_settings, set_keys, user_decided


def _grating(n: int, period: float, amplitude: float) -> np.ndarray:
    """(n, n, 3) a sinusoid along x about grey 0.5."""
    x = np.arange(n, dtype=np.float32)
    row = 0.5 + amplitude * np.sin(2 * np.pi * (x + 0.5) / period)
    return np.repeat(np.tile(row, (n, 1))[..., None], 3, axis=2)


def test_a_grating_as_fine_as_the_cells_is_lost_whole():
    """Cells of one period average each period to its mean: the residual is the whole grating, whose mean
    square is amplitude² / 2."""
    amplitude = 0.2
    image = _grating(64, 8, amplitude)
    mask = np.ones((64, 64), bool)
    res = grid_residual(image, mask, 8.0)
    assert float((res**2).mean()) == pytest.approx(amplitude**2 / 2, rel=1e-3)
    got = exterior_ceilings([image], [mask], {"cell": 8.0})
    assert got["cell"] == pytest.approx(-10 * math.log10(amplitude**2 / 2), abs=0.05)
    assert got["pixels"] == 64 * 64  # the frame's edge is not an outline: nothing mixes in there
    inner = np.zeros((64, 64), bool)
    inner[8:40, 8:40] = True  # a mask's own outline is eroded by a pixel
    assert exterior_ceilings([image], [inner], {"cell": 8.0})["pixels"] == 30 * 30


def test_a_grid_draws_a_linear_ramp_exactly_away_from_the_image_edge():
    """Cell averages of an affine image are its values at the cell centres, and linear interpolation between
    them is the ramp itself (an independent oracle: nothing but the ramp's formula)."""
    n, cell = 64, 8
    y, x = np.mgrid[0:n, 0:n].astype(np.float32)
    ramp = 0.1 + 0.004 * x + 0.007 * y
    image = np.repeat(ramp[..., None], 3, axis=2)
    res = grid_residual(image, np.ones((n, n), bool), float(cell))
    inner = res[cell : n - cell, cell : n - cell]  # beyond the outer cell centres the grid holds its edge value
    assert np.abs(inner).max() < 1e-5
    assert np.abs(grid_residual(image, np.ones((n, n), bool), 0.5)).max() == 0.0  # sub-pixel cells draw all


def test_a_plain_garment_beside_skin_is_drawn_exactly_its_neighbours_do_not_enter_its_cells():
    n = 64
    image = np.full((n, n, 3), 0.8, np.float32)  # skin
    image[:, : n // 2 + 3] = (0.2, 0.3, 0.6)  # a plain garment up to a boundary inside a cell
    mask = np.zeros((n, n), bool)
    mask[:, : n // 2 + 3] = True
    got = exterior_ceilings([image], [mask], {"preset": 6.0})
    assert got["preset"] == MAX_DB
    # the same cells over the whole image smear the boundary: the mask is what keeps the skin out
    whole = exterior_ceilings([image], [np.ones((n, n), bool)], {"preset": 6.0})
    assert whole["preset"] < 40
    # uint8 frames read as [0, 1]
    as_bytes = exterior_ceilings([np.round(image * 255).astype(np.uint8)], [mask], {"preset": 6.0})
    assert as_bytes["preset"] == MAX_DB


def test_finer_cells_draw_a_pattern_coarser_cells_cannot():
    """A grating of a 6-pixel period: cells of 6 pixels lose it, cells of 2 pixels keep most of it."""
    image = _grating(96, 6, 0.25)
    got = exterior_ceilings([image], [np.ones((96, 96), bool)], {"coarse": 6.0, "fine": 2.0})
    assert got["coarse"] == pytest.approx(-10 * math.log10(0.25**2 / 2), abs=0.1)
    assert got["fine"] > got["coarse"] + 6


@pytest.mark.parametrize(
    "ceiling, preset_cell, footprint, expected",
    [(19.7, 0.022, 0.0039, CELL_PIXELS * 0.0039),  # dots under the preset's cells: two pixels' footprint
     (PATTERN_DB + 5, 0.022, 0.0039, 0.0),  # a plain garment: the preset's
     (19.7, 0.0115, 0.0060, 0.0),  # two pixels no finer than the preset's cells: the preset's
     (19.7, 0.022, 0.0, 0.0)],  # no footprint measured: the preset's
)  # fmt: skip
def test_the_colour_cell_is_two_pixels_where_the_presets_cells_lose_the_pattern(ceiling, preset_cell, footprint,
                                                                                expected):  # fmt: skip
    ceilings = {"clothing": {"preset": ceiling, "fine": 28.0}, "hair": {"preset": PATTERN_DB + 10, "fine": 45.0}}
    assert colour_cell(ceilings, preset_cell, footprint) == pytest.approx(expected, abs=1e-5)
    assert colour_cell({}, preset_cell, footprint) == 0.0  # no exterior part to draw


def test_the_scenes_colour_cell_reaches_training_unless_the_config_sizes_the_colour_grids(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps({"decisions": {"nerf": {"color_cell": 0.0077}}}))
    assert scene_settings(path, {}, []) == {"nerf": {"color_cell": 0.0077}}
    for own in ({"nerf": {"color_max_res": 256}}, {"nerf": {"color_levels": 7}}, {"nerf": {"color_cell": 0.01}}):
        user_set = user_decided(set_keys([own]), 1)
        assert user_set and scene_settings(path, {}, user_set) == {}, own
    # a key of the NeRF the scene does not follow leaves the decision
    assert scene_settings(path, {}, user_decided(set_keys([{"nerf": {"width": 32}}]), 1)) == {
        "nerf": {"color_cell": 0.0077}
    }


@pytest.mark.slow
def test_a_patterned_exterior_gets_fine_colour_cells_and_a_plain_one_the_presets(tiny_training, tmp_path):
    """The same capture and fit, its clothing painted with 2-pixel checks or one flat colour: the decision
    follows the frames (at 64² a 1.5-m body is ~25 mm a pixel, so the preset here is 16 nodes along the
    box, ~140 mm cells)."""
    from delta.scene.analysis import analyze

    t = tiny_training["tight"]
    scenes = {}
    for kind in ("checks", "plain"):
        record = tmp_path / f"{kind}.h5"
        shutil.copy(t["record"], record)
        with h5py.File(record, "r+") as h5:
            images = h5["images"][:]
            cloth = (h5["clothing"][:] > 0) & (h5["person"][:] > 127)
            y, x = np.mgrid[0 : images.shape[1], 0 : images.shape[2]]
            checks = ((x // 2 + y // 2) % 2).astype(bool)
            paint = np.where(checks[..., None], (230, 230, 230), (20, 40, 160)) if kind == "checks" else (90, 60, 40)
            images[cloth] = np.broadcast_to(paint, images.shape)[cloth]
            h5["images"][...] = images
        scenes[kind] = analyze(record, t["init"], t["body"], 0.1, 16, size=64, frames=6, colour_res=16)
    checks, plain = scenes["checks"], scenes["plain"]
    foot = checks["evidence"]["samples"]["pixel_footprint_mm"] / 1000
    assert checks["decisions"]["nerf"]["color_cell"] == pytest.approx(CELL_PIXELS * foot, rel=0.01)
    evidence = checks["evidence"]["colour"]
    assert (
        evidence["parts"]["clothing"]["preset"]
        < PATTERN_DB
        < plain["evidence"]["colour"]["parts"]["clothing"]["preset"]
    )
    assert evidence["preset_cell_mm"] == pytest.approx(1000 * evidence["box_m"] / 15, rel=1e-3)
    assert "clothing" in evidence["why"] and "nerf" not in plain["decisions"]
    # the cells were measured against the box the avatar's exterior gets: the same room, the same framing
    from delta.body.model import load_body_model
    from delta.data.frames import load_frames
    from delta.models.init import load_init
    from delta.training.presets import resolve
    from delta.training.run import build_avatar

    room = checks["decisions"]["render"]["max_dist"]
    st = resolve("fast", {"resolution": 32, "render": {"max_dist": room}, "nerf": {"max_res": 16, "levels": 3}})
    data = load_frames(t["record"], st.resolution, st.background, st.box_margin)
    avatar = build_avatar(load_body_model(t["body"]), st, load_init(t["init"], data), data, 1, "cpu")
    lo, hi = avatar.nerf.encoding.lo, avatar.nerf.encoding.hi
    assert float((hi - lo).max()) == pytest.approx(evidence["box_m"], abs=1e-3)
    # without the preset's colour grids (a PE field, or a caller that does not say) nothing is decided
    none = analyze(tmp_path / "checks.h5", t["init"], t["body"], 0.1, 16, size=64, frames=6)
    assert "nerf" not in none["decisions"] and "colour" not in none["evidence"]
