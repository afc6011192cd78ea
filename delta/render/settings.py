"""How rays are sampled and rendered: the renderer's and the occupancy grid's settings (torch-free: the
workflow resolves presets from them before any job starts)."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass
class OccupancySettings:
    enabled: bool = False
    resolution: int = 64
    """Cells along the longest side of the NeRF's box."""
    update_every: int = 16
    """Training steps between re-evaluations of the density at the cells."""
    threshold: float = 0.5
    """Density σ (1/m) above which a cell is occupied (σΔ = 0.01 at Δ = 2 cm), or the mean over cells if lower."""
    decay: float = 0.95
    """Per update, the kept maximum decays by this factor before the new density is folded in."""
    warmup: int = 100
    """Steps of each stage before the grid marks cells from the NeRF's density alone; without ``early``
    no sample is skipped before it."""
    early: int = 0
    """Steps before a first, guarded use of the grid (0, or at or past ``warmup``: none, the grid waits
    for ``warmup``). From ``early`` to ``warmup`` the cells within ``early_shell`` of the canonical body
    stay occupied whatever the young field's density there, so a wide room's empty space is skipped
    early and a thin garment's cells, not yet dense, are not emptied for good."""
    early_shell: float = 0.05
    """How far from the canonical body (m) the cells stay occupied until ``warmup`` (with ``early``)."""
    carry: bool = True
    """Stage 2 starts from stage 1's grid (its kept densities, the occupied set re-grown by F_e's
    reach) instead of every cell occupied until its own ``warmup``."""


@dataclasses.dataclass
class RenderSettings:
    samples: int = 24
    """Samples per ray, the last at the mesh or far bound."""
    box_margin: float = 0.25
    """How far around the posed body's box the exterior may exist (m); never less than a ``max_dist``
    that bounds the exterior (:func:`room_margin`)."""
    k: int = 6
    sigma: float = 0.1
    max_dist: float = 0.2
    """Samples farther than this from every body vertex are empty and not evaluated."""
    shell: float = 0.0
    """The soft shell (m; 0: off): exterior density farther than this from the body costs, rising to its full
    cost at ``max_dist`` (the ray's ``shell_depth``; the loss ``weights.shell``). A frame seen from one side
    leaves an exterior's depth free along its rays; the shell puts it nearest the body the views allow."""
    sil_sigma: float = 1.0
    """Softness of the silhouette in pixels²."""
    sil_k: int = 16
    sil_hard_value: bool = True
    """The silhouette's value is the exact coverage of the pixel centre (the ray hits the mesh); its
    gradient is the soft silhouette's (straight-through). The soft union over many sub-pixel
    triangles lies ~1 px outside the true edge at 128², and the mask losses shrank the body by
    about that much (the hard coverage was 2/3 of the person) when they read its value."""
    probe: int = 32
    """Probe points a ray that find where it passes within ``max_dist`` of the body; samples go there only."""
    probe_cell: float = 0.02
    """Voxel size of the distance grid the probes read (m)."""
    contact_cell: float = 0.0
    """Tell body surfaces in contact apart (a hand on the hip): a sample also looks for another surface
    than its nearest vertex's among one vertex per voxel of this side (m) of the canonical space; its
    map from there is a second candidate and the denser one renders (``deformers/knn.py``; 0: off)."""
    round_trip: bool = True
    """Keep a sample only where its canonical point's nearest canonical vertex maps it back to the sample
    (``deformers/knn.py``): no clothing or hair density carried into empty space beside another part
    (a sleeve's ghost beside the torso when the arms are crossed). Needs ``max_dist`` ≤ 1 m (a grid)."""
    knn_vertices: str = "base"
    """Backward skinning over the ``base`` mesh's vertices (before upsampling; 4× fewer) or ``all``."""
    hair_carriage: str = "nearest"
    """What carries a hair layer's samples to the canonical space: ``nearest``, the body vertices nearest
    each (as every layer), or ``head``: bound to the head, by the nearest head vertex's map blended into
    the nearest vertices' by the ratio of the distances to the body and to the head (a strand beside the
    neck halfway, one lying on the shoulder by the shoulder; ``deformers/knn.py``). On the long-haired talker
    and on loose the hair region gains 0.4–1.3 dB with it and the whole image loses 0.06–0.23 dB on held-out
    poses: strands that rest on a shoulder turn with the head (docs/method.md). ``height``: the same blend
    by the canonical height of the sample's kNN point instead, the body's below the shoulders' joints, the
    head's above the head's joint, linear between (hair hangs from the head and comes to rest on the
    trunk; on loose the hair between the other two, the whole image as with the distances). Exports still pose
    the exterior's mesh by the nearest vertices."""
    perturb: bool = True
    early_cull: bool = True
    """Before the kNN query, drop samples that the distance grid puts beyond ``max_dist`` of the body
    (with √3 cells of slack: the grid's error) or whose rough canonical point (the nearest vertex's
    map, ``deformer.rough_canonical``) lies outside the occupancy grid's occupied set grown by
    ``EARLY_GROW`` cells; the exact tests still run on the samples that pass."""
    occupancy: OccupancySettings = dataclasses.field(default_factory=OccupancySettings)
    """The canonical occupancy grid that skips samples in empty space (training updates it)."""
