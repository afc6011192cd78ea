"""A layer's support: the cells around where it is seen, grown by whole cells, and a field confined to it."""

import torch

from delta.models.layer_support import Confined, in_cells, support_of


class Flat(torch.nn.Module):
    """Density 7 and grey everywhere."""

    def forward(self, x):
        return torch.full((len(x), 3), 0.5), torch.full((len(x),), 7.0)

    def density(self, x):
        return self(x)[1]

    def color_cell(self):
        return 0.01


def test_the_support_is_the_seen_cells_grown_by_whole_cells():
    seen = torch.tensor([[0.005, 0.005, 0.005], [0.305, 0.005, 0.005]])
    sup = support_of(seen, cell=0.02, grow=2)
    # cells on the world's grid: each seen point's cell [0, 0.02) and two cells either way, nothing beyond
    axis = torch.tensor([-0.045, -0.035, -0.005, 0.015, 0.055, 0.065])
    inside = sup(torch.stack([axis, torch.full_like(axis, 0.005), torch.full_like(axis, 0.005)], 1))
    assert inside.tolist() == [False, True, True, True, True, False]
    corner = torch.tensor([[0.055, 0.055, -0.035], [0.065, 0.045, 0.045], [0.305, -0.035, 0.055]])
    assert sup(corner).tolist() == [True, False, True]  # a cube, not a ball; the second point's own cube
    assert in_cells(corner, sup.lo, sup.cell, sup.cells).tolist() == [True, False, True]
    assert not bool(sup(torch.tensor([[0.15, 0.005, 0.005], [5.0, 5.0, 5.0], [-5.0, 0.0, 0.0]])).any())
    assert int(sup.cells.sum()) == 2 * 5**3  # two disjoint cubes of 5³ cells
    empty = support_of(torch.zeros(0, 3))
    assert not bool(empty(torch.zeros(4, 3)).any())


def test_a_confined_field_keeps_its_colour_and_has_no_density_outside():
    sup = support_of(torch.zeros(1, 3), cell=0.1, grow=0)
    field = Confined(Flat(), sup)
    x = torch.tensor([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05], [-0.05, 0.0, 0.0]])
    rgb, sigma = field(x)
    assert sigma.tolist() == [7.0, 0.0, 0.0] and field.density(x).tolist() == [7.0, 0.0, 0.0]
    assert torch.equal(rgb, torch.full((3, 3), 0.5)) and field.color_cell() == 0.01
    moved = field.to(torch.float64)  # the cells are buffers: they travel with the module
    assert moved.cells.dtype == torch.bool and moved.lo.dtype == torch.float64


def test_cells_ruled_out_leave_the_grown_margin_but_never_a_seen_cell():
    seen = torch.tensor([[0.005, 0.005, 0.005]])
    # ruled out: the seen cell itself, one cell and two cells along +x, and a point far outside the grid
    behind = torch.tensor([[0.006, 0.004, 0.005], [0.025, 0.005, 0.005], [0.045, 0.005, 0.005], [9.0, 0.0, 0.0]])
    sup = support_of(seen, cell=0.02, grow=2, behind=behind)
    axis = torch.tensor([-0.035, -0.015, 0.005, 0.025, 0.045])
    inside = sup(torch.stack([axis, torch.full_like(axis, 0.005), torch.full_like(axis, 0.005)], 1))
    assert inside.tolist() == [True, True, True, False, False]
    assert int(sup.cells.sum()) == 5**3 - 2  # the cube less the two ruled-out cells
    assert torch.equal(support_of(seen, 0.02, 2, torch.zeros(0, 3)).cells, support_of(seen, 0.02, 2).cells)


def test_the_support_rays_are_close_enough_to_meet_every_cell():
    from delta.cameras.models import OrthographicCamera
    from delta.models.layer_support import CELL, ray_grid, ray_step

    body = torch.tensor([[0.0, -0.8, 0.0], [0.0, 0.8, 0.0]])
    # a pixel spans 2 / (s W) m: 3.9 mm at 512 (the stride's rays are 7.8 mm apart, under half a 2-cm cell),
    # 62.5 mm at 32 (rays 1 cm apart: six a pixel)
    for width, stride, step in ((512, 2, 2.0), (32, 2, 0.16), (512, 1, 1.0)):
        camera = OrthographicCamera(scale=1.0, trans=(0.0, 0.0), width=width, height=width)
        assert abs(ray_step(camera, body, stride) - step) < 1e-6 and abs(CELL - 0.02) < 1e-12
    grid = ray_grid(4, 0.5)
    assert grid.shape == (64, 2) and grid[0].tolist() == [0.25, 0.25] and grid[1].tolist() == [0.75, 0.25]
    assert float(grid.max()) == 3.75


def test_hair_may_lie_over_clothing_and_nothing_over_hair():
    from delta.models.layer_support import may_cover

    assert may_cover("clothing", ("clothing", "hair")) == ("hair",)
    assert may_cover("hair", ("clothing", "hair")) == ()
    assert may_cover("hair", ("hair",)) == ()
