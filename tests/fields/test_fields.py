"""Encodings and fields: known values, exact interpolation of hand-set grids, initial states, caps."""

from __future__ import annotations

import math

import pytest
import torch

from delta.fields.encodings import GridEncoding, PositionalEncoding, make_encoding, positional_encoding
from delta.fields.networks import (
    MAX_LOG_DENSITY,
    MLP,
    DeformationField,
    active_units,
    FieldSpec,
    LayeredNeRF,
    NeRFField,
    VertexField,
    time_features,
)

D = torch.float64
BOUNDS = torch.tensor([[-1.0, 0.0, 2.0], [1.0, 3.0, 4.0]])
SMALL_GRID = FieldSpec(encoding="grid", levels=2, features=2, base_res=4, max_res=8, depth=2, width=32)
SMALL_PE = FieldSpec(encoding="pe", num_freqs=3, depth=2, width=32, skip=0)


def inside_points(n: int, seed: int, dtype=torch.float32) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=gen, dtype=dtype)
    return BOUNDS[0].to(dtype) + u * (BOUNDS[1] - BOUNDS[0]).to(dtype)


# ----------------------------------------------------------------- positional encoding
def test_positional_encoding_values():
    x = torch.tensor([[0.25, -0.5]], dtype=D)
    pe = positional_encoding(x, 2)
    s, pi = math.sqrt(0.5), math.pi
    # [x | sin(π x), sin(2π x) | cos(π x), cos(2π x)], frequency-major, coordinates inside
    expected = [0.25, -0.5, s, -1.0, 1.0, math.sin(-pi), s, 0.0, 0.0, -1.0]
    torch.testing.assert_close(pe[0], torch.tensor(expected, dtype=D), rtol=0, atol=1e-15)
    no_input = positional_encoding(x, 2, include_input=False)
    torch.testing.assert_close(no_input, pe[:, 2:], rtol=0, atol=0)


@pytest.mark.parametrize("num_freqs,dim", [(0, 3), (1, 3), (4, 2), (10, 3)])
def test_positional_encoding_dims_and_general_values(num_freqs, dim):
    gen = torch.Generator().manual_seed(num_freqs)
    x = torch.randn(5, dim, generator=gen, dtype=D)
    pe = positional_encoding(x, num_freqs)
    assert pe.shape == (5, dim * (1 + 2 * num_freqs))
    assert positional_encoding(x, num_freqs, include_input=False).shape == (5, dim * 2 * num_freqs)
    for k in range(num_freqs):
        f = math.pi * 2.0**k
        sin_block = pe[:, dim + k * dim : dim + (k + 1) * dim]
        cos_block = pe[:, dim * (1 + num_freqs) + k * dim : dim * (1 + num_freqs) + (k + 1) * dim]
        torch.testing.assert_close(sin_block, torch.sin(f * x), rtol=0, atol=1e-12)
        torch.testing.assert_close(cos_block, torch.cos(f * x), rtol=0, atol=1e-12)


def test_positional_encoding_module_normalises_to_the_box():
    enc = PositionalEncoding(3, BOUNDS)
    assert enc.out_dim == 21
    x = torch.stack([BOUNDS[0], BOUNDS[1], BOUNDS.mean(0)])
    out = enc(x)
    torch.testing.assert_close(out[:, :3], torch.tensor([[-1.0] * 3, [1.0] * 3, [0.0] * 3]), rtol=0, atol=1e-6)
    torch.testing.assert_close(out[2], positional_encoding(torch.zeros(1, 3), 3)[0], rtol=0, atol=1e-6)


# ----------------------------------------------------------------- grid encoding
def set_grids(enc: GridEncoding, fns) -> None:
    """Set feature c of every level to fns[c](x, y, z) at the world positions of the grid nodes."""
    lo, hi = enc.lo.double(), enc.hi.double()
    with torch.no_grad():
        for grid, shape in zip(enc.grids, enc.shapes):
            node = [lo[a] + (hi[a] - lo[a]) * torch.arange(shape[a], dtype=D) / (shape[a] - 1) for a in range(3)]
            # layout (1, C, D, H, W): z along D, y along H, x along W
            z, y, x = torch.meshgrid(node[2], node[1], node[0], indexing="ij")
            for c, fn in enumerate(fns):
                grid[0, c] = fn(x, y, z).float()


def test_grid_resolutions():
    enc = GridEncoding(BOUNDS, levels=6, features=4, base_res=16, max_res=128)
    assert enc.resolutions[0] == 16 and enc.resolutions[-1] == 128
    assert enc.resolutions == sorted(enc.resolutions) and enc.out_dim == 24
    # BOUNDS spans 2 × 3 × 2: the longest side (y) gets 128 nodes, x and z the same cell size
    assert [tuple(g.shape) for g in enc.grids][-1] == (1, 4, 86, 128, 86)
    assert enc.shapes[-1] == (86, 128, 86)
    assert GridEncoding(BOUNDS, levels=1, features=2, base_res=5, max_res=9).resolutions == [5]


def test_grid_reproduces_trilinear_functions_exactly():
    enc = GridEncoding(BOUNDS, levels=3, features=2, base_res=3, max_res=7)
    linear = lambda x, y, z: x + 2 * y + 3 * z  # noqa: E731
    trilinear = lambda x, y, z: x * (y - 1) * z  # noqa: E731  (in the span trilinear interpolation reproduces)
    set_grids(enc, [linear, trilinear])
    p = inside_points(200, 0)
    out = enc(p)
    assert out.shape == (200, 6)
    x, y, z = p.double().unbind(-1)
    for level in range(3):
        torch.testing.assert_close(out[:, 2 * level].double(), linear(x, y, z), rtol=0, atol=2e-5)
        torch.testing.assert_close(out[:, 2 * level + 1].double(), trilinear(x, y, z), rtol=0, atol=2e-5)
    # at the box corners and centre too
    corners = torch.tensor([[-1.0, 0.0, 2.0], [1.0, 3.0, 4.0], [1.0, 0.0, 4.0], [0.0, 1.5, 3.0]])
    torch.testing.assert_close(enc(corners)[:, 0], corners @ torch.tensor([1.0, 2.0, 3.0]), rtol=0, atol=2e-5)
    # float64 in, float64 out
    assert enc(p.double()).dtype == D


def test_grid_far_outside_reads_zero():
    enc = GridEncoding(BOUNDS, levels=2, features=3, base_res=4, max_res=6, init_std=1.0)
    with torch.no_grad():
        for g in enc.grids:
            g.add_(5.0)  # no zero features anywhere inside
    far = torch.tensor([[5.0, 1.0, 3.0], [0.0, -4.0, 3.0], [0.0, 1.0, 100.0], [-1e6, 1e6, 1e6]])
    assert torch.equal(enc(far), torch.zeros(4, 6))
    assert bool((enc(inside_points(50, 1)).abs() > 0).all())


def test_grid_fades_to_zero_within_one_cell_outside():
    """Just outside the box the features fall linearly to 0 over one cell (zero padding), then stay 0."""
    enc = GridEncoding(BOUNDS, levels=1, features=1, base_res=5, max_res=5)
    set_grids(enc, [lambda x, y, z: torch.ones_like(x)])
    cell_x = 2.0 / (enc.shapes[0][0] - 1)  # x is shorter than y: fewer nodes, same cell size
    xs = torch.tensor([1.0, 1.0 + 0.25 * cell_x, 1.0 + 0.5 * cell_x, 1.0 + cell_x, 1.0 + 2 * cell_x])
    p = torch.stack([xs, torch.full_like(xs, 1.5), torch.full_like(xs, 3.0)], -1)
    torch.testing.assert_close(enc(p)[:, 0], torch.tensor([1.0, 0.75, 0.5, 0.0, 0.0]), rtol=0, atol=1e-5)


def test_make_encoding():
    assert isinstance(make_encoding("pe", BOUNDS, num_freqs=4), PositionalEncoding)
    assert make_encoding("pe", BOUNDS, num_freqs=4).out_dim == 27
    g = make_encoding("grid", BOUNDS, levels=2, features=3, base_res=4, max_res=8)
    assert isinstance(g, GridEncoding) and g.out_dim == 6 and g.resolutions == [4, 8]
    with pytest.raises(ValueError):
        make_encoding("hash", BOUNDS)


# ----------------------------------------------------------------- networks
def test_mlp_skip_connection_shapes():
    mlp = MLP(5, 2, depth=3, width=8, skip=1)
    assert mlp.hidden[2].in_features == 8 + 5 and mlp.out.in_features == 8
    assert mlp(torch.randn(4, 5)).shape == (4, 2)


def test_active_units_by_hand():
    """2 -> 3 -> 3 -> 1: units 0 and 1 read x and y, unit 2 is -x - y - 10 (below zero on all of [0, 1]²); the
    second layer passes each unit on (identity), so the unit only unit 2 feeds is inactive too."""
    mlp = MLP(2, 1, depth=2, width=3)
    with torch.no_grad():
        mlp.hidden[0].weight.copy_(torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, -1.0]]))
        mlp.hidden[0].bias.copy_(torch.tensor([0.0, 0.0, -10.0]))
        mlp.hidden[1].weight.copy_(torch.eye(3))
        mlp.hidden[1].bias.zero_()
    x = torch.rand(500, 2, generator=torch.Generator().manual_seed(0))
    assert active_units(mlp, x) == [2, 2]
    with torch.no_grad():
        mlp.hidden[0].bias[2] = 1.5  # -x - y + 1.5 > 0 near the origin
    assert active_units(mlp, x) == [3, 3]
    assert active_units(mlp, x + 1.0) == [2, 2]  # on [1, 2]² it is below zero again


def test_deformation_field_active_units_over_its_box_and_times():
    torch.manual_seed(2)
    field = DeformationField(SMALL_PE, BOUNDS, scale=0.05, time_freqs=3)
    times = time_features(torch.linspace(0, 1, 5), 3)
    fresh = field.active_units(times, points=2000)
    assert len(fresh) == 2 and min(fresh) >= 28  # 32 units a layer, (nearly) all active somewhere at the start
    with torch.no_grad():
        field.head.hidden[1].bias[:20] = -1e3  # 20 units of the last layer pushed below zero for good
    assert field.active_units(times, points=2000)[1] == fresh[1] - 20
    # the time inputs count: a unit that reads only the time is active at some times, not at others
    with torch.no_grad():
        field.head.hidden[0].weight[0].zero_()
        field.head.hidden[0].weight[0, -1] = 1.0  # cos(3πτ): +1 at τ = 0, -1 at τ = 1/3
        field.head.hidden[0].bias[0] = -0.5
    only_late = time_features(torch.tensor([1 / 3]), 3)
    assert field.active_units(only_late, points=200)[0] < field.active_units(times, points=200)[0]


@pytest.mark.parametrize("spec", [SMALL_GRID, SMALL_PE], ids=["grid", "pe"])
def test_nerf_density_capped_and_finite(spec):
    torch.manual_seed(0)
    field = NeRFField(spec, BOUNDS)
    x = inside_points(64, 2)
    rgb, sigma = field(x)
    assert rgb.shape == (64, 3) and sigma.shape == (64,)
    assert bool((sigma >= 0).all()) and bool((rgb >= 0).all()) and bool((rgb <= 1).all())
    with torch.no_grad():
        field.head.out.bias.fill_(1e4)
    rgb, sigma = field(x)
    cap = math.exp(MAX_LOG_DENSITY)
    assert MAX_LOG_DENSITY == 15.0
    torch.testing.assert_close(sigma, torch.full_like(sigma, cap), rtol=1e-6, atol=0)
    assert bool(torch.isfinite(sigma).all()) and bool(torch.isfinite(rgb).all())
    (sigma.sum() + rgb.sum()).backward()
    for p in field.parameters():
        assert p.grad is None or bool(torch.isfinite(p.grad).all())
    with torch.no_grad():
        field.head.out.bias.fill_(-1e4)
    _, sigma = field(x)
    assert bool((sigma >= 0).all()) and bool(torch.isfinite(sigma).all()) and float(sigma.detach().max()) == 0.0


@pytest.mark.parametrize("spec", [SMALL_GRID, SMALL_PE], ids=["grid", "pe"])
def test_nerf_starts_nearly_empty(spec):
    torch.manual_seed(1)
    field = NeRFField(spec, BOUNDS, density_bias=-2.0)
    assert field.head.out.bias[-1].item() == -2.0
    _, sigma = field(inside_points(64, 3))
    assert bool((sigma < math.exp(-2.0) * 3).all()) and bool((sigma > math.exp(-2.0) / 3).all())


@pytest.mark.parametrize("spec", [SMALL_GRID, SMALL_PE], ids=["grid", "pe"])
def test_offset_field_starts_at_exactly_zero(spec):
    torch.manual_seed(2)
    field = VertexField(spec, BOUNDS, "offset", scale=0.04)
    out = field(inside_points(30, 4))
    assert torch.equal(out, torch.zeros(30, 3))
    # after a step it moves, and never beyond the scale
    with torch.no_grad():
        field.head.out.bias.fill_(100.0)
    assert bool((field(inside_points(30, 4)).abs() <= 0.04).all())


@pytest.mark.parametrize("spec", [SMALL_GRID, SMALL_PE], ids=["grid", "pe"])
def test_albedo_field_starts_near_the_init_colour(spec):
    torch.manual_seed(3)
    colour = torch.tensor([0.8, 0.6, 0.5])
    field = VertexField(spec, BOUNDS, "albedo", init=colour)
    out = field(inside_points(30, 5))
    torch.testing.assert_close(field.head.out.bias.detach(), torch.log(colour / (1 - colour)), rtol=0, atol=1e-6)
    torch.testing.assert_close(out, colour.expand(30, 3), rtol=0, atol=2e-2)
    # an init colour outside [0.02, 0.98] is clamped
    clamped = VertexField(spec, BOUNDS, "albedo", init=torch.tensor([0.0, 1.0, 0.5]))
    torch.testing.assert_close(torch.sigmoid(clamped.head.out.bias.detach()), torch.tensor([0.02, 0.98, 0.5]),
                               rtol=0, atol=1e-6)  # fmt: skip


def test_albedo_field_starts_exactly_at_the_init_colour():
    torch.manual_seed(3)
    colour = torch.tensor([0.8, 0.6, 0.5])
    field = VertexField(SMALL_GRID, BOUNDS, "albedo", init=colour)
    torch.testing.assert_close(field(inside_points(30, 5)), colour.expand(30, 3), rtol=0, atol=1e-5)


def test_per_vertex_detail_starts_at_the_field_and_reaches_single_vertices():
    """A detail table adds to the raw output: zero at the start (the field alone), and one vertex's
    colour can move without its neighbours (a grid cell cannot)."""
    import dataclasses

    torch.manual_seed(5)
    spec = dataclasses.replace(SMALL_GRID, vertex_detail=True)
    colour = torch.tensor([0.8, 0.6, 0.5])
    plain = VertexField(SMALL_GRID, BOUNDS, "albedo", init=colour)
    torch.manual_seed(5)
    field = VertexField(spec, BOUNDS, "albedo", init=colour, num_vertices=30)
    x = inside_points(30, 5)
    torch.testing.assert_close(field(x), plain(x), rtol=0, atol=0)
    target = field(x).detach().clone()
    target[7] = torch.tensor([0.1, 0.9, 0.2])  # one vertex's own colour
    opt = torch.optim.Adam([field.detail], lr=0.1)
    for _ in range(300):
        opt.zero_grad()
        ((field(x) - target) ** 2).sum().backward()
        opt.step()
    torch.testing.assert_close(field(x), target, rtol=0, atol=1e-3)
    assert float(field.detail.detach()[torch.arange(30) != 7].abs().max()) < 1e-3  # the others untouched
    # offsets stay within their scale whatever the detail
    off = VertexField(dataclasses.replace(SMALL_PE, vertex_detail=True), BOUNDS, "offset", 0.04, num_vertices=30)
    with torch.no_grad():
        off.detail.fill_(50.0)
    assert bool((off(x).abs() <= 0.04).all()) and float(off(x).detach().min()) > 0.039
    with pytest.raises(ValueError, match="reads its 30 vertices"):
        field(x[:10])
    with pytest.raises(ValueError, match="vertex count"):
        VertexField(spec, BOUNDS, "albedo")
    with pytest.raises(ValueError, match="vertex_detail 'yes'"):
        FieldSpec(vertex_detail="yes")


def test_vertex_field_rejects_unknown_kind():
    with pytest.raises(ValueError):
        VertexField(SMALL_GRID, BOUNDS, "normals")


@pytest.mark.parametrize("spec", [SMALL_GRID, SMALL_PE], ids=["grid", "pe"])
def test_deformation_field_starts_at_zero_and_learns(spec):
    torch.manual_seed(4)
    field = DeformationField(spec, BOUNDS, scale=0.05)
    x_c = inside_points(40, 6).requires_grad_()
    posed_ref = torch.randn(40, 3, requires_grad=True)
    out = field(x_c, posed_ref)
    assert torch.equal(out, torch.zeros(40, 3))
    target = torch.randn(40, 3, generator=torch.Generator().manual_seed(7))
    ((out - 0.01 * target) ** 2).sum().backward()
    # the output layer gets gradients at once; the pose cue is detached
    assert field.head.out.weight.grad.abs().sum() > 0 and field.head.out.bias.grad.abs().sum() > 0
    assert posed_ref.grad is None
    for p in field.parameters():
        assert p.grad is None or bool(torch.isfinite(p.grad).all())
    # after one step every parameter (encoding, hidden layers) is reached, and so is x_c
    opt = torch.optim.SGD(field.parameters(), lr=0.1)
    opt.step()
    opt.zero_grad()
    x_c.grad = None
    out = field(x_c, posed_ref)
    assert out.abs().max() > 0 and bool((out.abs() <= 0.05).all())
    ((out - 0.01 * target) ** 2).sum().backward()
    for name, p in field.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    assert x_c.grad is not None and x_c.grad.abs().sum() > 0


def test_time_features_by_hand():
    tau = torch.tensor([0.5, 0.0, float("nan")], dtype=D)
    f = time_features(tau, 2)
    # [sin(πτ), sin(2πτ) | cos(πτ), cos(2πτ)]
    torch.testing.assert_close(f[0], torch.tensor([1.0, 0.0, 0.0, -1.0], dtype=D), atol=1e-12, rtol=0)
    torch.testing.assert_close(f[1], torch.tensor([0.0, 0.0, 1.0, 1.0], dtype=D))
    assert torch.equal(f[2], torch.zeros(4, dtype=D))  # outside the sequence: the time-free input


def test_deformation_field_reads_the_time():
    torch.manual_seed(3)
    field = DeformationField(SMALL_PE, BOUNDS, scale=0.05, time_freqs=3)
    x_c, ref = inside_points(30, 1), torch.randn(30, 3)
    t1, t2 = time_features(torch.tensor(0.2), 3), time_features(torch.tensor(0.7), 3)
    assert torch.equal(field(x_c, ref, t1), torch.zeros(30, 3))  # still starts at exactly 0
    with torch.no_grad():
        for p in field.head.parameters():
            p.normal_(0, 0.3)
    a, b = field(x_c, ref, t1), field(x_c, ref, t2)
    assert (a - b).abs().max() > 1e-3  # the same point and pose at two times moves differently
    # no time = zero features; a field without time ignores it
    assert torch.equal(field(x_c, ref), field(x_c, ref, torch.zeros(6)))
    plain = DeformationField(SMALL_PE, BOUNDS, scale=0.05)
    assert plain.head.hidden[0].in_features == field.head.hidden[0].in_features - 6
    # gradients reach the time path's weights
    field(x_c, ref, t1).sum().backward()
    assert field.head.hidden[0].weight.grad[:, -6:].abs().sum() > 0


def test_nerf_colour_grid_can_be_finer_than_the_density_grid():
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    spec = FieldSpec("grid", levels=3, features=2, base_res=4, max_res=16, depth=1, width=16,
                     color_max_res=64, color_levels=4)  # fmt: skip
    nerf = NeRFField(spec, box)
    assert max(max(s) for s in nerf.encoding.shapes) == 16
    assert max(max(s) for s in nerf.color_encoding.shapes) == 64 and len(nerf.color_encoding.shapes) == 4
    same = NeRFField(FieldSpec("grid", levels=3, features=2, base_res=4, max_res=16, depth=1, width=16), box)
    assert same.color_encoding.shapes == same.encoding.shapes
    rgb, sigma = nerf(torch.rand(5, 3) * 2 - 1)
    assert rgb.shape == (5, 3) and sigma.shape == (5,)


@pytest.mark.parametrize("cell", [0.3, 0.1, 0.04, 0.013])
def test_a_colour_cell_sets_the_colour_grids_finest_node_spacing_at_the_grids_own_growth(cell):
    """``color_cell``: the colour grids' finest node spacing is at most the cell and less than a node finer
    (the longest side, 3 long, over the spacing), never coarser than the configured grid, and each level is at
    most the configured growth finer than the one before; the density's grids are untouched."""
    spec = FieldSpec("grid", levels=3, features=2, base_res=4, max_res=16, depth=1, width=8, color_cell=cell)
    nerf = NeRFField(spec, BOUNDS)
    assert nerf.encoding.resolutions == [4, 8, 16]
    res = nerf.color_encoding.resolutions
    if 3.0 / cell + 1 <= 16:  # the configured grid is finer already
        assert res == [4, 8, 16]
        return
    assert nerf.color_cell() <= cell + 1e-9 and 3.0 / (res[-1] - 2) > cell  # as coarse as the cell allows
    assert all(b / a <= 2.0 + 0.05 for a, b in zip(res, res[1:])), res  # growth 16/4 over two levels: 2
    assert len(res) > 3
    rgb, sigma = nerf(inside_points(7, 3, torch.float32))
    assert rgb.shape == (7, 3) and sigma.shape == (7,)


def test_a_colour_cell_is_capped_by_the_grids_nodes_and_a_configured_grid_wins_where_finer():
    from delta.fields.spec import MAX_COLOR_NODES

    spec = FieldSpec("grid", levels=5, features=2, base_res=12, max_res=96, color_cell=1e-4)
    fine, levels = spec.color_grid((1.0, 0.5, 0.5))
    nodes = fine * math.ceil(fine * 0.5) ** 2
    assert nodes <= MAX_COLOR_NODES * 1.02 and (fine + 1) * math.ceil((fine + 1) * 0.5) ** 2 > MAX_COLOR_NODES * 0.98
    assert levels > 5
    assert FieldSpec(max_res=96, color_max_res=300, color_cell=0.01).color_grid((1.0, 1.0, 1.0)) == (300, 6)
    assert FieldSpec(max_res=96).color_grid((1.0, 1.0, 1.0)) == (96, 6)  # no cell: as configured
    for bad in (-0.01, float("nan"), "fine"):
        with pytest.raises(ValueError, match="color_cell"):
            FieldSpec(color_cell=bad)


def test_finest_cell_is_the_grids_node_spacing_and_the_encodings_half_period():
    """A grid's finest cell is the distance between its finest level's nodes: a field that is 1 at one
    node and 0 at the others reads 1 there, 0.5 half a cell away and 0 a cell away. A PE's is half the
    period of its highest frequency: that feature is negated a cell away and repeats two cells away."""
    enc = GridEncoding(BOUNDS, levels=2, features=1, base_res=4, max_res=9)
    cell = enc.finest_cell()
    assert cell == pytest.approx(3.0 / 8)  # the longest side (y, 3 long) has 9 nodes
    with torch.no_grad():
        for g in enc.grids:
            g.zero_()
        enc.grids[-1][0, 0, 2, 4, 2] = 1.0  # the node (x, y, z) = (2, 4, 2) cells from the box's low corner
    spacing = (BOUNDS[1] - BOUNDS[0]) / (torch.tensor(enc.shapes[-1], dtype=torch.float32) - 1)  # per axis
    node = BOUNDS[0] + spacing * torch.tensor([2.0, 4.0, 2.0])
    along_y = torch.stack([node + torch.tensor([0.0, d * cell, 0.0]) for d in (0.0, 0.5, 1.0, -1.0)])
    torch.testing.assert_close(enc(along_y)[:, -1], torch.tensor([1.0, 0.5, 0.0, 0.0]), rtol=0, atol=1e-5)
    pe = PositionalEncoding(4, BOUNDS)
    cell = pe.finest_cell()
    assert cell == pytest.approx(3.0 / 16)
    x = inside_points(20, 3, D) * 0.5 + 0.5
    L = 4  # features: x, sin(2^k π x_n) for k < L (x y z each), then the cosines; the longest side is y
    highest = lambda p: pe(p)[:, [3 + 3 * (L - 1) + 1, 3 + 3 * L + 3 * (L - 1) + 1]]  # noqa: E731
    shift = torch.tensor([0.0, cell, 0.0], dtype=D)
    torch.testing.assert_close(highest(x + shift), -highest(x), rtol=0, atol=1e-9)
    torch.testing.assert_close(highest(x + 2 * shift), highest(x), rtol=0, atol=1e-9)
    nerf = NeRFField(FieldSpec("grid", levels=2, features=2, base_res=4, max_res=9, depth=1, width=8,
                               color_max_res=17), BOUNDS)  # fmt: skip
    assert nerf.color_cell() == pytest.approx(3.0 / 16)
    assert NeRFField(SMALL_PE, BOUNDS).color_cell() == pytest.approx(3.0 / 8)


# ----------------------------------------------------------------- SCARF's ReLU density with training noise
RELU_PE = FieldSpec(encoding="pe", num_freqs=3, depth=2, width=32, skip=0, density_activation="relu",
                    density_noise=1.0, density_noise_steps=100)  # fmt: skip


def test_relu_density_is_relu_of_raw_and_noise_only_while_set():
    torch.manual_seed(0)
    nerf = NeRFField(RELU_PE, BOUNDS)
    x = inside_points(512, 0)
    raw = nerf.raw_density(x)
    torch.testing.assert_close(nerf(x)[1], torch.relu(raw))  # no noise unless a training step sets it
    torch.testing.assert_close(nerf.density(x), torch.relu(raw))
    nerf.set_noise(0.5, seed=3)
    noise = torch.randn(raw.shape, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(nerf(x)[1], torch.relu(raw + 0.5 * noise))
    torch.testing.assert_close(nerf.density(x), torch.relu(raw))  # the occupancy grid and export: never noisy
    nerf.set_noise(0.0)
    torch.testing.assert_close(nerf(x)[1], torch.relu(raw))


def test_noise_decays_linearly_to_zero():
    assert [RELU_PE.noise_at(s) for s in (0, 25, 50, 100, 500)] == [1.0, 0.75, 0.5, 0.0, 0.0]
    assert FieldSpec().noise_at(0) == 0.0


def test_noise_gives_a_density_pushed_below_zero_a_gradient_again():
    torch.manual_seed(0)
    nerf = NeRFField(RELU_PE, BOUNDS)
    with torch.no_grad():
        nerf.head.out.bias[-1] = -3.0  # every raw density well below zero: a dead ReLU
    x = inside_points(2048, 1)
    nerf(x)[1].sum().backward()
    assert nerf.head.out.bias.grad[-1] == 0
    nerf.zero_grad()
    nerf.set_noise(1.0, seed=0)
    nerf(x)[1].sum().backward()
    assert nerf.head.out.bias.grad[-1] > 0  # the samples the noise lifts above zero pull it up


@pytest.mark.parametrize("bad", [{"density_activation": "softplus"}, {"density_noise": -1.0},
                                 {"density_noise_steps": 0}])  # fmt: skip
def test_bad_density_settings_name_the_key(bad):
    from delta import DeltaError
    from delta.training.presets import resolve

    with pytest.raises(DeltaError, match="training.nerf"):
        resolve("paper", {"nerf": bad})


def test_the_paper_preset_has_scarfs_density_and_nerf_only_start():
    from delta.training.presets import resolve

    spec = resolve("paper").avatar.nerf
    assert (spec.density_activation, spec.density_noise, spec.density_noise_steps) == ("relu", 1.0, 5000)
    assert resolve("fast").avatar.nerf.density_activation == "exp"
    assert (resolve("paper").stage1.nerf_warmup, resolve("fast").stage1.nerf_warmup) == (400, 0)


@pytest.mark.parametrize("spec", [SMALL_GRID, SMALL_PE])
def test_layered_nerf_is_one_medium_of_its_layers(spec):
    """σ = Σ σ_l and c = Σ σ_l c_l / σ, layer by layer against each NeRFField on its own; a one-layer
    stack is the plain NeRF built from the same seed."""
    torch.manual_seed(3)
    nerf = LayeredNeRF(spec, BOUNDS)
    with torch.no_grad():  # layers that differ visibly (a fresh one is nearly empty)
        for k, layer in enumerate(nerf.layers.values()):
            layer.head.out.bias[-1] = 1.0 + k
    x = inside_points(64, 4)
    rgb, sigma, sigmas = nerf.with_layers(x)
    parts = [nerf.layers[n](x) for n in ("clothing", "hair")]
    torch.testing.assert_close(sigmas, torch.stack([s for _, s in parts], -1))
    torch.testing.assert_close(sigma, parts[0][1] + parts[1][1])
    mix = (parts[0][1][:, None] * parts[0][0] + parts[1][1][:, None] * parts[1][0]) / sigma[:, None]
    torch.testing.assert_close(rgb, mix)
    torch.testing.assert_close(nerf.density(x), sigma)
    torch.testing.assert_close(nerf(x)[0], rgb)
    torch.manual_seed(5)
    one = LayeredNeRF(spec, BOUNDS, ("hair",))
    torch.manual_seed(5)
    plain = NeRFField(spec, BOUNDS)
    for a, b in zip(one(x), plain(x)):
        torch.testing.assert_close(a, b)
    assert nerf.color_cell() == plain.color_cell()


@pytest.mark.parametrize("names", [(), ("hair", "hair"), ("hat",)])
def test_layered_nerf_refuses_unknown_or_repeated_layers(names):
    with pytest.raises(ValueError, match="exterior layers"):
        LayeredNeRF(SMALL_GRID, BOUNDS, names)


def test_layered_nerf_stays_finite_where_a_layer_is_empty_or_at_the_cap():
    """One layer's density underflowing to exactly 0, the other's at the cap e^15: colour, density and every
    gradient finite, the colour the dense layer's."""
    nerf = LayeredNeRF(SMALL_GRID, BOUNDS)
    with torch.no_grad():
        nerf.layers["clothing"].head.out.bias[-1] = -200.0  # exp(-200) is 0 in float32
        nerf.layers["hair"].head.out.bias[-1] = 100.0  # capped
    x = inside_points(32, 7)
    rgb, sigma, sigmas = nerf.with_layers(x)
    assert bool((sigmas[:, 0] == 0).all()) and bool(torch.isfinite(sigma).all())
    torch.testing.assert_close(rgb, nerf.layers["hair"](x)[0])
    (rgb.sum() + sigma.log().sum() + sigmas.sum()).backward()
    assert all(bool(torch.isfinite(p.grad).all()) for p in nerf.parameters() if p.grad is not None)
    both_empty = LayeredNeRF(SMALL_GRID, BOUNDS)
    with torch.no_grad():
        for layer in both_empty.layers.values():
            layer.head.out.bias[-1] = -200.0
    rgb, sigma, _ = both_empty.with_layers(x)
    assert bool((sigma == 0).all()) and bool(torch.isfinite(rgb).all())
    rgb.sum().backward()
    assert all(bool(torch.isfinite(p.grad).all()) for p in both_empty.parameters() if p.grad is not None)


@pytest.mark.parametrize("inside", [True, False])
def test_the_sparse_trilinear_matrix_is_grid_samples_interpolation(inside):
    """Points inside the box, on its faces and nodes, and outside it (zeros padding): values and the grid's
    gradient as grid_sample gives them."""
    from delta.fields.encodings import _Interpolate, trilinear_matrix

    gen = torch.Generator().manual_seed(1)
    shape = (5, 7, 3)  # nx, ny, nz
    grid = torch.randn(1, 2, shape[2], shape[1], shape[0], generator=gen, dtype=torch.float64, requires_grad=True)
    span = 1.0 if inside else 1.4
    xn = (torch.rand(400, 3, generator=gen, dtype=torch.float64) * 2 - 1) * span
    xn[:6] = torch.tensor([[-1.0, -1, -1], [1, 1, 1], [1, -1, 0.5], [0, 0, 0], [-0.5, 1 / 3, -1], [1, 0.2, 1]])
    want = torch.nn.functional.grid_sample(grid, xn.view(1, -1, 1, 1, 3), align_corners=True).view(2, -1).T
    W, WT = trilinear_matrix(xn, shape)
    got = _Interpolate.apply(grid.view(2, -1).T, W, WT)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    weights = torch.randn(400, 2, generator=gen, dtype=torch.float64)
    (g_want,) = torch.autograd.grad((want * weights).sum(), grid)
    (g_got,) = torch.autograd.grad((_Interpolate.apply(grid.view(2, -1).T, W, WT) * weights).sum(), grid)
    torch.testing.assert_close(g_got, g_want, rtol=0, atol=1e-12)
    assert (want[6:].abs().sum(1) == 0).any() != inside  # outside the box some points read zeros


def test_a_vertex_field_keeps_its_vertices_encoding_and_rebuilds_it_when_they_change():
    from delta.fields.encodings import GridEncoding, PositionalEncoding

    gen = torch.Generator().manual_seed(2)
    bounds = torch.tensor([[-1.0, -1.0, -0.5], [1.0, 1.5, 0.5]])
    x = torch.rand(300, 3, generator=gen) * (bounds[1] - bounds[0]) + bounds[0]
    for enc in (GridEncoding(bounds, levels=3, features=2, base_res=4, max_res=16), PositionalEncoding(4, bounds)):
        first = enc.at_fixed(x)
        torch.testing.assert_close(first, enc(x), rtol=0, atol=1e-6)
        kept = enc._fixed
        enc.at_fixed(x)
        assert enc._fixed is kept, "the same points: nothing rebuilt"
        x.add_(0.01)  # moved in place: rebuilt for the new places
        torch.testing.assert_close(enc.at_fixed(x), enc(x), rtol=0, atol=1e-6)
        assert enc._fixed is not kept
        with torch.no_grad():
            enc.lo.sub_(0.1)  # a loaded state's box: rebuilt too
        torch.testing.assert_close(enc.at_fixed(x), enc(x), rtol=0, atol=1e-6)
        y = x.clone().requires_grad_(True)  # points that need their gradient go the plain way
        (g,) = torch.autograd.grad(enc.at_fixed(y).sum(), y)
        assert g.abs().sum() > 0
    grid = GridEncoding(bounds, levels=2, features=2, base_res=4, max_res=8)
    (g_fixed,) = torch.autograd.grad((grid.at_fixed(x) ** 2).sum(), grid.grids[1])
    (g_plain,) = torch.autograd.grad((grid(x) ** 2).sum(), grid.grids[1])
    torch.testing.assert_close(g_fixed, g_plain, rtol=1e-5, atol=1e-7)
