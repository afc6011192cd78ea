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
