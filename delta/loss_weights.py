"""The λ of each training loss term (torch-free: the workflow resolves presets from them before any job
starts; the terms are in ``delta.losses``)."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass
class LossWeights:
    """λ of each term; defaults are the paper's body weights (§4.2)."""

    pixel: float = 1.0
    """Huber loss of the composite colour."""
    semantic: float = 0.0005
    """ID-MRF on rendered patches (stage 2 only)."""
    exterior: float = 0.5
    """L1 between the NeRF mask s_v and the exterior mask."""
    exterior_layers: float = 0.5
    """L1 between each exterior layer's opacity and its own mask (clothing, hair), averaged over the
    layers, where the exterior is in layers."""
    layer_shares: float = 0.05
    """Cross-entropy between the layers' shares of the density each exterior ray sees and its pixel's
    layers, where the exterior is in layers: a layer pushed out of its region wins it back (an opacity's
    L1 cannot; not the paper's, measured in docs/method.md)."""
    empty_background: float = 0.0
    """The exterior's optical depth on rays the person mask puts on the background (off: 0)."""
    shell: float = 0.1
    """The exterior's optical depth beyond the soft shell (``render.shell``; no term where that is 0)."""
    distortion: float = 0.0
    """Per metre: the exterior's weight along each ray spread in depth (Mip-NeRF 360's distortion,
    ``delta.render.volume.distortion``; off: 0)."""
    face_points: float = 0.0
    """Where the record tracks a face: the posed face points against the detected ones (Huber of their
    distance over the image's size), so that training keeps the face where the frame shows it (off: 0)."""
    track: float = 0.0
    """Per metre, stage 2: across the rays, the distance between the canonical points where the two ends of a
    point of the exterior followed through the training frames are seen (``delta.data.tracks``), moving F_e
    alone (off: 0, in every preset: it lowered loose's held-out views, docs/method.md)."""
    silhouette: float = 0.001
    """Huber between the soft mesh silhouette and the person mask."""
    interior_mask: float = 30.0
    """Mesh silhouette must cover the visible body."""
    skin: float = 1.0
    """Mesh colour must match the image on the visible body."""
    inside: float = 40.0
    """Mesh silhouette must stay inside the person mask."""
    skin_inside: float = 0.01
    """Occluded body colour pulled to the average skin colour."""
    edge: float = 500.0
    """Relative edge loss between the mesh with and without offsets."""
    offset: float = 400.0
    """Squared offsets, per region (see ``offset_region_weights``)."""
    offset_region_weights: dict = dataclasses.field(
        default_factory=lambda: {"body": 2.0, "face": 3.0, "hands": 12.0, "feet": 2.0, "eyes": 3.0, "mouth": 3.0}
    )
    """body : face : hands = 2 : 3 : 12 as in the paper (feet like the body, eyes/mouth like the face)."""
    vertex_detail: float = 0.01
    """Mean squared per-vertex detail of the offset and albedo fields (``vertex_detail`` fields only)."""
    huber_delta: float = 0.1
    """Where the Huber loss turns from quadratic to linear."""
