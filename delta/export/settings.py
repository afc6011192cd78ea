"""What an export makes and how (config group ``export``)."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass
class ExportSettings:
    """Export options; the CLI flags and the config keys ``export: {...}`` fill them."""

    grid: int = 192
    """Marching-cubes cells along the longest side of the NeRF's canonical box (~1 cm voxels for a 2 m box)."""
    threshold: float = 10.0
    """Density level of the clothing/hair surface (1/m): a 1 cm slab at σ = 10 is ~10 % opaque."""
    smooth: int = 3
    """Taubin smoothing steps of the clothing mesh (0: none); Taubin does not shrink the surface."""
    decimate: int = 60000
    """Target face count of the clothing mesh after quadric decimation (0: keep every face)."""
    min_component_faces: int = 200
    """Connected components of the clothing mesh with fewer faces are removed (floaters)."""
    turntable_frames: int = 36
    """Frames of the turntable video (one full turn)."""
    fps: int = 12
    """Frame rate of the videos."""
    sidebyside: int = 4
    """Test frames written as reference | render | error images."""
    chunk: int = 65536
    """NeRF queries per batch when sampling the density grid."""

    def __post_init__(self) -> None:
        if self.grid < 8:
            raise ValueError(f"export.grid: {self.grid} (expected at least 8 cells)")
        if self.threshold <= 0:
            raise ValueError(f"export.threshold: {self.threshold} (expected a positive density)")
        for key in ("smooth", "decimate", "min_component_faces", "sidebyside"):
            if getattr(self, key) < 0:
                raise ValueError(f"export.{key}: {getattr(self, key)} (expected ≥ 0)")
        if self.turntable_frames < 1 or self.fps < 1:
            raise ValueError("export.turntable_frames and export.fps must be at least 1")
