"""What an export makes and how (config group ``export``)."""

from __future__ import annotations

import dataclasses

from delta.settings import check

_f = dataclasses.field


@dataclasses.dataclass
class ExportSettings:
    """Mesh export and videos of the trained avatars (results/{dataset}/{subject}/export/).

    The config section ``export`` and the options of ``delta export`` are generated from these fields.
    """

    grid: int = _f(default=192, metadata={"minimum": 8, "maximum": 1024})
    """Marching-cubes cells along the longest side of the NeRF's canonical box (~1 cm voxels for a 2 m box)."""
    threshold: float = _f(default=10.0, metadata={"exclusive_minimum": 0})
    """Density level of the clothing/hair surface (1/m): a 1 cm slab at σ = 10 is ~10 % opaque."""
    smooth: int = _f(default=3, metadata={"minimum": 0})
    """Taubin smoothing steps of the clothing mesh (0: none); Taubin does not shrink the surface."""
    decimate: int = _f(default=60000, metadata={"minimum": 0})
    """Target face count of the clothing mesh after quadric decimation (0: keep every face)."""
    color_spacing: float = _f(default=1.0, metadata={"minimum": 0})
    """Longest edge of the clothing/hair mesh, in the capture's pixels at the person's distance, where
    the NeRF's colours are read at its vertices: longer edges are split, down to half the NeRF colour
    grid's finest cell (finer sampling shows nothing the model holds). 0: the decimated mesh as is."""
    outside_views: int = _f(default=12, metadata={"minimum": 0, "maximum": 360})
    """Views around the body (at each of a side view and two from above) that decide the clothing/hair
    surface's outside: the faces none of them sees (the NeRF's walls under a skirt, beside the legs, the cap
    under a hem) are left out, so the surface is a sheet as a garment is. 0: the level set's closed surface."""
    min_component_faces: int = _f(default=200, metadata={"minimum": 0})
    """Connected components of the clothing mesh with fewer faces are removed (floaters)."""
    turntable_frames: int = _f(default=36, metadata={"minimum": 2, "maximum": 720})
    """Frames of the turntable video (one full turn)."""
    fps: int = _f(default=12, metadata={"minimum": 1, "maximum": 120})
    """Frame rate of the videos."""
    novel_frames: int = _f(default=48, metadata={"minimum": 1, "maximum": 10000})
    """At most this many frames of novel_pose.mp4 (the test-pose frames, or the capture's frames when it
    has none), evenly spaced."""
    sidebyside: int = _f(default=4, metadata={"minimum": 0, "maximum": 50})
    """Test frames written as reference | render | error images."""
    chunk: int = _f(default=65536, metadata={"minimum": 1})
    """NeRF queries per batch when sampling the density grid."""

    def __post_init__(self) -> None:
        check(self, "export")


#: What each part of an export writes (``delta export --part``): the meshes take seconds, the videos
#: render whole frames (minutes to hours at the capture's size), so evaluation and the applications,
#: which read only the clothing surface, need not wait for the videos.
PARTS = ("meshes", "videos", "all")
#: The settings each part reads; each workflow job is given only its part's, so that a change to the
#: videos does not make the meshes again (nor rerun the evaluation that reads them).
PART_FIELDS = {
    "meshes": (
        "grid",
        "threshold",
        "smooth",
        "decimate",
        "color_spacing",
        "outside_views",
        "min_component_faces",
        "chunk",
        "fps",
    ),
    "videos": ("turntable_frames", "fps", "novel_frames", "sidebyside"),
}


def part_settings(settings: ExportSettings | dict, part: str) -> dict:
    """The fields of ``settings`` (an object or the config's mapping) that ``part`` reads (all for ``all``)."""
    values = vars(settings) if isinstance(settings, ExportSettings) else settings
    names = PART_FIELDS.get(part, tuple(f.name for f in dataclasses.fields(ExportSettings)))
    return {name: values[name] for name in names if name in values}
