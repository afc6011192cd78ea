"""What a neural field is: its encoding, network and density activation (torch-free: the workflow
resolves presets from it before any job starts)."""

from __future__ import annotations

import dataclasses
import math

#: The most nodes a colour grid decided from ``color_cell`` may have (a finest level of 2^24 nodes with
#: two features holds 128 MB of parameters and three times that in its gradient and Adam's moments).
MAX_COLOR_NODES = 1 << 24


@dataclasses.dataclass
class FieldSpec:
    """Architecture of one field (a preset fills these)."""

    encoding: str = "grid"
    """``pe`` (PE + deep MLP, the paper's) or ``grid`` (dense multi-resolution grids + small MLP)."""
    num_freqs: int = 10
    """PE frequencies (``pe``)."""
    levels: int = 6
    features: int = 4
    base_res: int = 16
    max_res: int = 128
    depth: int = 2
    """Hidden layers of the MLP head."""
    width: int = 64
    skip: int = -1
    """Hidden layer after which the encoding is concatenated again (-1: none; the paper: 4)."""
    color_max_res: int = 0
    """NeRF ``grid``: finest resolution of the colour grids (0: ``max_res``). Colour carries the
    texture, density only the shape, so the colour grid can be finer at little cost."""
    color_levels: int = 0
    """NeRF ``grid``: levels of the colour grids (0: ``levels``)."""
    color_cell: float = 0.0
    """NeRF ``grid``: the colour grids' finest cell (metres; 0: from ``color_max_res``). Where set, the finest
    colour resolution is the field's box over it (never coarser than ``color_max_res``, at most
    :data:`MAX_COLOR_NODES` nodes) and levels are added at the grids' own growth. Finer cells sharpen a
    pattern's edges only as far as the frames agree where they lie (docs/tradeoff.md, colour cells)."""
    density_activation: str = "exp"
    """NeRF: ``exp`` (σ = exp(raw), capped; starts nearly empty) or ``relu`` (σ = max(raw + noise, 0),
    SCARF's, with Gaussian noise on raw while training: without it a ReLU or exp density pushed below
    zero everywhere by the mask losses gets no gradient again)."""
    density_noise: float = 0.0
    """NeRF: standard deviation of the noise on raw density at a stage's first step (SCARF: 1)."""
    density_noise_steps: int = 5000
    """NeRF: steps over which that noise decays linearly to 0 (SCARF: 5000)."""
    vertex_detail: bool = False
    """Offsets and albedo: a free value per mesh vertex added to the field's raw output, so that detail
    reaches the mesh's own resolution (Anny's face edges are 2.7 mm long, while a grid with ``max_res``
    96 over the body's 1.9-m box has 2-cm cells: eyes and lips blur). The field gives the smooth rest and
    what no frame sees (a vertex no ray reaches keeps a zero detail); ``weights.vertex_detail`` pulls the
    detail toward zero so that the field explains what it can."""

    def __post_init__(self):
        if not (isinstance(self.color_cell, (int, float)) and math.isfinite(self.color_cell) and self.color_cell >= 0):
            raise ValueError(f"color_cell {self.color_cell!r}: expected a number of metres ≥ 0")
        if not isinstance(self.vertex_detail, bool):
            raise ValueError(f"vertex_detail {self.vertex_detail!r}: expected true or false")
        if self.density_activation not in ("exp", "relu"):
            raise ValueError(f"density_activation {self.density_activation!r}: expected 'exp' or 'relu'")
        if self.density_noise < 0 or self.density_noise_steps < 1:
            raise ValueError(f"density_noise {self.density_noise} must be ≥ 0 and density_noise_steps "
                             f"{self.density_noise_steps} ≥ 1")  # fmt: skip

    def colour_nodes(self) -> int:
        """The configured colour grids' finest resolution (nodes along the box; 0: no grids, ``pe``)."""
        return (self.color_max_res or self.max_res) if self.encoding == "grid" else 0

    def color_grid(self, extent: tuple[float, float, float]) -> tuple[int, int]:
        """The colour grids' (finest resolution, levels) for a box of ``extent`` (metres a side): the
        configured ones, or finer where ``color_cell`` asks for it (levels added so that each is at most
        the configured growth finer than the one before)."""
        res, levels = self.color_max_res or self.max_res, self.color_levels or self.levels
        longest = max(extent)
        if self.color_cell <= 0 or longest <= 0:
            return res, levels
        cells = math.prod(e / longest for e in extent)  # nodes of a resolution-r grid ≈ r³ × this
        cap = int((MAX_COLOR_NODES / max(cells, 1e-12)) ** (1 / 3))
        fine = min(max(math.ceil(longest / self.color_cell - 1e-9) + 1, res), max(cap, res))
        if fine > res and levels > 1 and res > self.base_res:
            growth = (res / self.base_res) ** (1 / (levels - 1))
            levels += math.ceil(math.log(fine / res) / math.log(growth) - 1e-9)
        return fine, levels

    def noise_at(self, step: int) -> float:
        """The raw-density noise's standard deviation at a stage's ``step`` (0-based)."""
        return self.density_noise * max(0.0, 1.0 - step / self.density_noise_steps)
