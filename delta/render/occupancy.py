"""An occupancy grid over the NeRF's canonical box: skip samples where the exterior is empty.

instant-NGP / nerfacc style. A coarse grid (``resolution`` cells along the box's longest
side, near-cubic cells) keeps a decaying maximum of the NeRF density at its cells,

    d_c <- max(decay · d_c, σ(centre_c + jitter)),      occupied_c = d_c > min(threshold, mean_c d_c),

re-evaluated every ``update_every`` training steps once ``warmup`` steps have passed. The
renderer then drops samples whose canonical point (after backward skinning, before F_e and
the NeRF) lands in an empty cell: they cost neither the NeRF query nor F_e, and contribute
σ = 0 exactly as if the NeRF had returned ~0 there. Points outside the box are kept (the
grid says nothing about them). With F_e (stage 2) the occupied set is dilated by F_e's
largest displacement, since the check happens before F_e moves the point; stage 2 starts from
stage 1's grid so grown (``carry``), not from an all-occupied one. The point F_e has moved is
tested again against the set itself (``settled``): the grid's densities are the NeRF's at canonical
points, where the moved point is looked up, so a sample F_e carries into an empty cell is dropped
before the NeRF as in stage 1. The mean in the
threshold (instant-NGP's) keeps a still nearly uniform field (early training) from being
emptied all at once: the denser part of the cells stays; a perfectly flat one keeps every cell.

Non-differentiable; its buffers live in the model's state, so checkpoints resume exactly.

No per-frame visual hull: with one camera per frame every sample of a ray projects to that
ray's own pixel, so dropping samples outside the frame's (dilated) person mask means dropping
whole rays outside the person — exactly the rays whose exterior loss teaches the NeRF to be
empty there (rays are already drawn only in the person's box plus a margin). A hull over many
frames needs the canonical mapping, which is what this grid accumulates.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn

from delta.render.settings import OccupancySettings


class OccupancyGrid(nn.Module):
    def __init__(self, bounds: torch.Tensor, settings: OccupancySettings, dilation: float = 0.0,
                 body: torch.Tensor | None = None):  # fmt: skip
        """``bounds`` (2, 3) box; ``dilation``: grow the occupied set by this much (m) around occupied cells;
        ``body``: (V, 3) canonical body vertices, whose cells within ``settings.early_shell`` an early
        update keeps (:meth:`update`)."""
        super().__init__()
        self.threshold, self.decay = float(settings.threshold), float(settings.decay)
        lo, hi = bounds[0].float(), bounds[1].float()
        extent = hi - lo
        self.shape = tuple(max(1, int(math.ceil(settings.resolution * float(e / extent.max())))) for e in extent)
        self.register_buffer("lo", lo.clone())
        self.register_buffer("hi", hi.clone())
        cell = float((extent / torch.tensor(self.shape)).min())
        self.dilation = _cells(dilation, cell)
        self.register_buffer("density", torch.zeros(self.shape))
        self.register_buffer("occupied", torch.ones(self.shape, dtype=torch.bool))
        self.register_buffer("active", torch.tensor(False))
        # derived from the body, not saved: checkpoints from before it load unchanged
        grow = _cells(settings.early_shell, cell)
        #: how far from the body the shell's cells may reach (m): the vertex's own cell and the cells grown
        self.shell_reach = (grow + 1) * cell
        shell = torch.zeros(self.shape, dtype=torch.bool, device=lo.device)
        if body is not None and settings.early:
            shell = _grow(self.cells_holding(body.detach().to(lo)), grow)
        self.register_buffer("shell", shell, persistent=False)

    @property
    def cell(self) -> torch.Tensor:
        """(3,) cell size along x, y, z."""
        return (self.hi - self.lo) / torch.tensor(self.shape, dtype=self.lo.dtype, device=self.lo.device)

    def centres(self) -> torch.Tensor:
        """(N, 3) cell centres, x-major (the flattening of ``density``)."""
        axes = [torch.arange(n, dtype=self.lo.dtype, device=self.lo.device) + 0.5 for n in self.shape]
        ijk = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        return self.lo + ijk * self.cell

    def cell_index(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 3) integer cells of ``points`` (N, 3) (0 where outside the grid) and (N,) whether inside."""
        shape = torch.tensor(self.shape, device=points.device)
        fijk = torch.floor((points.detach() - self.lo) / self.cell)
        inside = ((fijk >= 0) & (fijk < shape)).all(-1)
        return torch.where(inside[:, None], fijk, torch.zeros_like(fijk)).long(), inside

    def cells_holding(self, points: torch.Tensor) -> torch.Tensor:
        """A boolean grid of the cells that hold at least one of ``points`` (N, 3) (those outside are not counted)."""
        ijk, inside = self.cell_index(points)
        ijk = ijk[inside]
        out = torch.zeros(self.shape, dtype=torch.bool, device=points.device)
        out[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
        return out

    def reset(self) -> None:
        """Forget everything (a stage's start): every cell occupied, the grid not used until the next update."""
        self.density.zero_()
        self.occupied.fill_(True)
        self.active.fill_(False)

    @torch.no_grad()
    def update(self, density_fn: Callable[[torch.Tensor], torch.Tensor], seed: int, chunk: int = 65536,
               early: bool = False) -> None:  # fmt: skip
        """Fold σ at jittered cell centres into the decaying maximum; the grid is used from now on.

        ``early``: an update before the warm-up's end, which keeps the body's shell of cells occupied too.
        The jitter comes from ``seed`` alone (the step), so a resumed run makes the same update.
        """
        gen = torch.Generator().manual_seed(int(seed))
        x = self.centres()
        x = x + ((torch.rand(x.shape, generator=gen) - 0.5).to(x) * self.cell)
        new = torch.cat([density_fn(x[s : s + chunk]).float() for s in range(0, len(x), chunk)])
        self.density.copy_(torch.maximum(self.density * self.decay, new.view(self.shape)))
        self._mark(early)

    def carry_over(self) -> bool:
        """Start a stage from the grid as loaded (the previous stage's), its occupied set re-derived
        from the kept densities with this grid's dilation (stage 2's F_e reach). False, and nothing
        changed, when the loaded grid was never updated (a stage 1 shorter than its warm-up)."""
        if not bool(self.active):
            return False
        self._mark()
        return True

    def _mark(self, early: bool = False) -> None:
        """The occupied set from the kept densities (and, ``early``, the body's shell), grown by the
        dilation; the grid is used from now on."""
        core = self._core() | self.shell if early else self._core()
        self.occupied.copy_(_grow(core, self.dilation))
        self.active.fill_(True)

    def _core(self) -> torch.Tensor:
        """The cells the kept densities mark occupied, before any dilation."""
        occ = self.density > min(self.threshold, float(self.density.mean()))
        if not occ.any():
            # no cell above the field's own mean: a flat field (σ underflowed to 0 everywhere, as a
            # PE NeRF at a grid's learning rate does) says nothing about where the exterior is, and an
            # empty grid would cut the NeRF off from every gradient for good: keep every cell
            occ = torch.ones_like(occ)
        return occ

    def contains(self, points: torch.Tensor, grow: int = 0, settled: bool = False) -> torch.Tensor:
        """(N,) bool: the point lies in an occupied cell, or outside the grid (never skipped).

        ``grow``: in the occupied set grown by this many cells (a test for a point known only
        to within that many cells; the renderer's cull before the kNN query). ``settled``: the point
        is where the NeRF will be queried (after F_e): tested against the occupied set without F_e's
        dilation (``grow`` then counts from that set).
        """
        if settled:
            occupied = _grow(self._settled(), grow)
        else:
            occupied = self._grown(grow) if grow > 0 else self.occupied
        ijk, inside = self.cell_index(points)
        occ = occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
        return occ | ~inside

    def _settled(self) -> torch.Tensor:
        """The occupied set without the dilation, cached until the kept densities or the set change."""
        if not self.dilation:
            return self.occupied
        key = (self.density._version, self.density.data_ptr(), self.occupied._version)
        if getattr(self, "_settled_key", None) != key:
            self._settled_cache, self._settled_key = self._core(), key
        return self._settled_cache

    def _grown(self, cells: int) -> torch.Tensor:
        """The occupied set grown by ``cells``, cached until ``occupied`` changes in place (an update,
        a checkpoint load: both bump its version counter)."""
        key = (cells, self.occupied._version, self.occupied.data_ptr())
        if getattr(self, "_grown_key", None) != key:
            self._grown_cache, self._grown_key = _grow(self.occupied, cells), key
        return self._grown_cache

    def fraction(self) -> float:
        """Share of the cells that are occupied."""
        return float(self.occupied.sum()) / self.occupied.numel()


def _cells(length: float, cell: float) -> int:
    """Whole cells that cover ``length`` (m) (0 for none)."""
    return int(math.ceil(length / cell - 1e-9)) if length > 0 else 0


def _grow(occupied: torch.Tensor, cells: int) -> torch.Tensor:
    """A boolean grid with every occupied cell's (2 cells + 1)³ neighbourhood occupied too."""
    if cells <= 0:
        return occupied
    k = 2 * cells + 1
    return F.max_pool3d(occupied[None, None].float(), k, stride=1, padding=cells)[0, 0] > 0
