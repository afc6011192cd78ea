"""A face detector's landmarks embedded on the body mesh, calibrated from rendered faces.

MediaPipe's face mesh gives 468 points a frame, in its own topology. To fit the body model's face to
them, each needs a place on the body mesh: a triangle and barycentric weights, which then follow the
shape, pose and expressions (:class:`delta.body.face_points.FacePoints`). Nobody ships that
correspondence for a license-free body model, so it is measured: the body's head is rendered by the
generator's ray caster from a spread of views and shapes, the detector runs on each render, and the
ray through each detected point finds the surface point it marks. Mapped back to the mean shape's rest
mesh, a landmark's hits agree to a few millimetres where it marks a feature of the face (eye corners,
nostrils, lips) and spread along the cheek where it marks the face's outline as seen (the jaw's contour
points slide with the view). The embedding keeps each landmark at the median of its hits, and only those
whose hits lie within ``max_spread`` of it: an outline point would pull the fit towards a fixed place that
the detector does not mean.

The calibration faces' mouths are closed, so the inner lips' points (where the lips part) hit where the
lips meet, the same few millimetres for both lips: the nearest triangle there was the upper lip's for the
lower lip's points too, which then could not follow the jaw (landmark 14 moved 1.4 mm with a fully open
jaw where the lower lip's outer centre moves 38 mm). A tracker that names its inner lips
(``inner_lips``: landmark ids by lip) has each placed on the nearest triangle of its own lip, the lower
lip being what opening the mouth moves (:func:`lip_triangles`).

Shapes: L landmarks (468), K kept.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import torch
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from delta import DeltaError
from delta.body.face_points import FacePoints, LandmarkEmbedding
from delta.body.lbs import lbs
from delta.body.model import REGION, BodyModel
from delta.cameras.models import PinholeCamera, look_at
from delta.geometry.closest import closest_point_on_triangles
from delta.synthetic import textures
from delta.synthetic.raycast import SceneMesh, render

log = logging.getLogger(__name__)

#: a landmark is kept when the median distance of its hits from their median is at most this (m)
MAX_SPREAD = 0.004
#: a landmark needs hits in at least this share of the views
MIN_HITS = 0.5
#: a face vertex is the jaw's (the lower lip's) when opening the mouth moves it at least this share of the
#: most it moves any face vertex, and the upper face's when at most ``1 - JAW_SHARE`` of it
JAW_SHARE = 0.5


@dataclasses.dataclass
class View:
    betas: torch.Tensor
    """(S,) shape of the rendered body."""
    yaw: float
    pitch: float
    """degrees: the camera's turn about the head (yaw about the vertical, pitch up)."""


def calibration_views(num_shape: int, yaws=(-24, -12, 0, 12, 24), pitches=(-10, 8), shapes: int = 3,
                      seed: int = 0) -> list[View]:  # fmt: skip
    """Every yaw x pitch for the mean shape and ``shapes - 1`` random ones (N(0, 0.7) coefficients)."""
    rng = np.random.default_rng(seed)
    betas = [np.zeros(num_shape)] + [rng.normal(0, 0.7, num_shape) for _ in range(shapes - 1)]
    return [View(torch.from_numpy(b), y, p) for b in betas for y in yaws for p in pitches]


HEAD_DISTANCE = 0.8
"""m from the face's centre to the calibration camera"""


def head_camera(centre: np.ndarray, width_m: float, view: View, resolution: int) -> PinholeCamera:
    """A camera 0.8 m from ``centre`` whose image is ``width_m`` / 0.55 wide there, turned as ``view`` says."""
    distance = HEAD_DISTANCE
    f = 0.55 * resolution * distance / width_m
    y, p = math.radians(view.yaw), math.radians(view.pitch)
    target = torch.from_numpy(centre).double()
    eye = target + distance * torch.tensor([math.sin(y) * math.cos(p), math.sin(p), math.cos(y) * math.cos(p)],
                                           dtype=torch.float64)  # fmt: skip
    R, _ = look_at(eye, target, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    K = torch.tensor([[f, 0, resolution / 2], [0, f, resolution / 2], [0, 0, 1]], dtype=torch.float64)
    return PinholeCamera(K, R, -R @ eye, torch.zeros(5, dtype=torch.float64), resolution, resolution)


#: the calibration renders' skin and background colours
SKIN = (0.85, 0.68, 0.58)
BACKGROUND = (0.8, 0.8, 0.78)


@dataclasses.dataclass
class HeadRender:
    image: np.ndarray
    """(H, W, 3) uint8 RGB."""
    vertices: np.ndarray
    """(V, 3) the rendered mesh's vertices."""
    camera: PinholeCamera
    face_width_px: float
    """The face region's width in the image at its centre's distance."""


def render_head(model: BodyModel, view: View, resolution: int = 512, expression: torch.Tensor | None = None,
                skin=SKIN, background=BACKGROUND, seed: int = 0) -> HeadRender:  # fmt: skip
    """The generator's textured body at rest (shape ``view.betas``, with an ``expression`` (E,) if given),
    its face filling about half the image, seen from ``view``; skin, eyes, brows and lips painted on the
    neutral face (they move with the expression, as a face's do)."""
    zero = torch.zeros(1, model.num_joints, 3, dtype=torch.float64)
    betas = view.betas[None].double()
    with torch.no_grad():
        rest = lbs(model, betas, zero).vertices[0].numpy()
        posed = rest if expression is None else lbs(model, betas, zero, expression[None].double()).vertices[0].numpy()
    faces, regions = model.faces.numpy(), model.regions.numpy()
    face = regions == REGION["face"]
    span = np.ptp(rest[face], 0)
    camera = head_camera(rest[face].mean(0), float(max(span[0], span[1])), view, resolution)
    features = textures.FaceFeatures(rest, regions)
    normals = trimesh.Trimesh(rest, faces, process=False).vertex_normals
    scene = SceneMesh(posed, faces, np.zeros(len(faces), np.int64), rest, normals, regions.astype(np.uint8))
    frame = render(scene, camera, lambda o, p, lab: textures.skin_albedo(p, lab.astype(np.int64), skin, features, seed),
                   textures.shading, background)  # fmt: skip
    width = float(span[0] * camera.K[0, 0] / HEAD_DISTANCE)
    return HeadRender(np.round(frame.image * 255).astype(np.uint8), posed, camera, width)


def _surface_hits(mesh: trimesh.Trimesh, camera: PinholeCamera, uv: np.ndarray):
    """(triangle (P,), barycentric (P, 3), ok (P,)) of the first surface along the rays through ``uv``."""
    origins, dirs = camera.rays(torch.from_numpy(uv.astype(np.float64)))
    tri, ray, loc = RayMeshIntersector(mesh).intersects_id(origins.numpy(), dirs.numpy(), multiple_hits=False,
                                                            return_locations=True)  # fmt: skip
    triangle, bary, ok = np.zeros(len(uv), np.int64), np.zeros((len(uv), 3)), np.zeros(len(uv), bool)
    if len(tri):
        triangle[ray], ok[ray] = tri, True
        bary[ray] = trimesh.triangles.points_to_barycentric(mesh.vertices[mesh.faces[tri]], loc)
    return triangle, bary, ok


def nearest_triangles(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, chunk: int = 64):
    """(P, 3) corners of the nearest of ``faces`` to each of (P, 3) ``points`` and (P, 3) the closest
    points on them (every triangle tried: a face region is a few thousand)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    corners, closest = np.zeros((len(points), 3), np.int64), np.zeros((len(points), 3))
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk]
        P, T = len(p), len(faces)
        q = closest_point_on_triangles(np.repeat(p, T, 0), np.tile(a, (P, 1)), np.tile(b, (P, 1)), np.tile(c, (P, 1)))
        q = q.reshape(P, T, 3)
        best = ((q - p[:, None]) ** 2).sum(-1).argmin(1)
        corners[s : s + P], closest[s : s + P] = faces[best], q[np.arange(P), best]
    return corners, closest


def jaw_motion(model: BodyModel) -> np.ndarray | None:
    """(V,) how far each vertex moves as the mouth opens (``jawOpen`` at 1, or a jaw joint's skinning
    weight); None where the body model has neither."""
    names = list(model.expression_names)
    if "jawOpen" in names and model.exprdirs is not None:
        return model.exprdirs[..., names.index("jawOpen")].norm(dim=-1).numpy()
    if "jaw" in model.joint_names:
        return model.weights[:, list(model.joint_names).index("jaw")].numpy()
    return None


def lip_triangles(model: BodyModel, surface: np.ndarray) -> dict[str, np.ndarray] | None:
    """The face triangles of each lip, ``upper`` (the upper face, which the jaw leaves) and ``lower`` (the
    jaw's), by :func:`jaw_motion`; None where the body model cannot open its mouth."""
    motion = jaw_motion(model)
    if motion is None or not motion[surface].max() > 0:
        return None
    share = motion / motion[surface].max()
    return {"upper": surface[(share[surface] <= 1 - JAW_SHARE).all(1)],
            "lower": surface[(share[surface] >= JAW_SHARE).all(1)]}  # fmt: skip


def calibrate(model: BodyModel, tracker, views: list[View], resolution: int = 512,
              max_spread: float = MAX_SPREAD, skin=SKIN) -> LandmarkEmbedding:  # fmt: skip
    """Embed ``tracker``'s landmarks (a callable: RGB uint8 frame -> (L, 3) (u, v, confidence)) on ``model``."""
    if not hasattr(tracker, "reset"):
        raise DeltaError("calibrate: the tracker needs reset() (each view is a new face)")
    zero = torch.zeros(1, model.num_joints, 3, dtype=torch.float64)
    faces, regions = model.faces.numpy(), model.regions.numpy()
    with torch.no_grad():
        template = lbs(model, torch.zeros(1, model.num_shape, dtype=torch.float64), zero).vertices[0].numpy()
    face = regions == REGION["face"]
    if not face.any():
        raise DeltaError(f"body model '{model.name}' has no face region to calibrate landmarks on")
    hits: list[list[np.ndarray]] = []
    for view in views:
        shot = render_head(model, view, resolution, skin=skin)
        mesh, camera = trimesh.Trimesh(shot.vertices, faces, process=False), shot.camera
        tracker.reset()
        found = tracker(shot.image)
        if not hits:
            hits = [[] for _ in range(len(found))]
        if found[0, 2] <= 0:
            log.warning("calibration view yaw %g pitch %g: no face found", view.yaw, view.pitch)
            continue
        tri, bary, ok = _surface_hits(mesh, camera, found[:, :2])
        on_template = np.einsum("pk,pkc->pc", bary, template[faces[tri]])
        for k in np.flatnonzero(ok & face[faces[tri]].any(1)):
            hits[k].append(on_template[k])
    if not hits:
        raise DeltaError("calibrate: no views")
    surface = faces[face[faces].all(1)]
    L = len(hits)
    spread, centres = np.full(L, np.nan), np.zeros((L, 3))
    for k, h in enumerate(hits):
        if len(h) >= MIN_HITS * len(views):
            h = np.asarray(h)
            centres[k] = np.median(h, 0)
            spread[k] = float(np.median(np.linalg.norm(h - centres[k], axis=1)))
    kept = np.flatnonzero(np.nan_to_num(spread, nan=np.inf) <= max_spread)
    if not len(kept):
        raise DeltaError(f"calibrate: no landmark's hits agree within {max_spread * 1000:g} mm over {len(views)} views")
    corners, closest = nearest_triangles(template, surface, centres[kept])
    lips, named = lip_triangles(model, surface), getattr(tracker, "inner_lips", {})
    if named and lips is None:
        log.warning("body model '%s' has no 'jawOpen' expression or 'jaw' joint: the inner lips' landmarks are "
                    "placed on the nearest lip, and may not follow the jaw", model.name)  # fmt: skip
    for lip, ids in named.items() if lips is not None else ():
        on = np.flatnonzero(np.isin(kept, ids))
        if len(on) and len(lips[lip]):
            corners[on], closest[on] = nearest_triangles(template, lips[lip], centres[kept[on]])
    bary = trimesh.triangles.points_to_barycentric(template[corners], closest).clip(0, 1)
    bary /= bary.sum(1, keepdims=True)
    points = FacePoints(torch.from_numpy(corners.astype(np.int64)), torch.from_numpy(bary))
    log.info("landmark embedding: %d of %d landmarks kept (hits within %.1f mm over %d views); median spread %.2f mm",
             len(kept), L, max_spread * 1000, len(views), 1000 * np.nanmedian(spread))  # fmt: skip
    return LandmarkEmbedding(kept.astype(np.int64), points, spread, len(views))
