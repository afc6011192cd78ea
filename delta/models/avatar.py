"""The hybrid avatar: body mesh with learned offsets and albedo + canonical NeRF exterior.

Per-frame pose and camera (and the shared shape) are parameters refined during
training; the networks are F_d (offsets), F_t (albedo), F_h (NeRF, only when the
capture has an exterior) and F_e (non-rigid deformation, stage 2).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import torch
from torch import nn

from delta.body.lbs import batch_rodrigues, lbs, posed_joints
from delta.body.model import REGION, BodyModel
from delta.body.parts import hair_span, head_vertices, lower_body_vertices
from delta.cameras.models import OrthographicCamera, PinholeCamera
from delta.deformers import knn as deformer
from delta.fields.networks import DeformationField, LayeredNeRF, NeRFField, VertexField, colour_logit, time_features
from delta.geometry.distance_grid import GRID_REACH
from delta.losses import mesh_edges
from delta.render.hybrid import PosedMesh, RayRender, exterior_surface, render_rays, room_margin
from delta.models.trajectory import Trajectory
from delta.models.spec import AvatarSpec
from delta.render.occupancy import OccupancyGrid

#: What carries a hair layer's samples to the canonical space (``render.hair_carriage``).
HAIR_CARRIAGES = ("nearest", "head", "height")


@dataclasses.dataclass
class InitParams:
    """Initial per-frame parameters (from the init fit), N frames."""

    betas: torch.Tensor
    """(S,) shape."""
    poses: torch.Tensor
    """(N, J, 3) axis-angle."""
    transl: torch.Tensor
    """(N, 3)."""
    camera: object
    """PinholeCamera (fixed) or OrthographicCamera with (N,) scale, (N, 2) translation."""
    expression: Optional[torch.Tensor] = None
    """(N, E) expression activations of a tracked face, or None (a still face: none modelled)."""


def knn_vertex_ids(body: BodyModel, which: str) -> torch.Tensor:
    """Vertices backward skinning searches: ``all``, or ``base`` (those an upsampled mesh kept from its base)."""
    if which == "all" or body.embed_bary is None:
        return torch.arange(body.num_vertices)
    if which != "base":
        raise ValueError(f"render.knn_vertices: '{which}' (expected 'base' or 'all')")
    return torch.nonzero(body.embed_bary.max(1).values > 1 - 1e-6).squeeze(1)


def mouth_prior(body: BodyModel, skin_color: torch.Tensor, shade) -> Optional[torch.Tensor]:
    """(V, 3) raw addition to the albedo field that starts the mouth's inside (the body's ``mouth`` region:
    cavity and tongue) at ``shade`` × the skin colour (a number, or one a channel), zeros elsewhere; None
    where the body has no mouth region or ``shade`` is 1 (the skin colour everywhere).

    No loss sees the inside of a mouth that no training frame opens; a held-out frame that opens it shows
    what the field holds there: its start, moved only as the lips' training moves their neighbours. Lit
    from outside, the inside is in shadow.
    """
    mouth = body.regions == REGION["mouth"]
    shade = torch.as_tensor(shade, dtype=torch.float32).expand(3)
    if bool((shade >= 1.0).all()) or not bool(mouth.any()):
        return None

    skin = skin_color.float().cpu()
    prior = torch.zeros(body.num_vertices, 3)
    prior[mouth.cpu()] = colour_logit(skin * shade) - colour_logit(skin)
    return prior


def _box(points: torch.Tensor, margin: float) -> torch.Tensor:
    return torch.stack([points.amin(0) - margin, points.amax(0) + margin])


def canonical_vertices(body: BodyModel) -> torch.Tensor:
    """(V, 3) the body's template in its canonical pose (the canonical space the fields live in)."""
    return lbs(body, torch.zeros(1, 1), body.canonical_pose[None].float()).vertices[0]


def modelled_vertices(body: BodyModel, capture: str) -> torch.Tensor:
    """(V,) bool: the vertices a ``capture`` models (a head-and-shoulders one not the lower body)."""
    if capture not in ("full", "upper"):
        raise ValueError(f"capture: '{capture}' (expected 'full' or 'upper')")
    if capture == "upper":
        return ~lower_body_vertices(body)
    return torch.ones(body.num_vertices, dtype=torch.bool, device=body.v_template.device)


def exterior_box(canonical: torch.Tensor, region: torch.Tensor, nerf_margin: float, max_dist: float) -> torch.Tensor:
    """(2, 3) the exterior fields' canonical box: the ``region``'s vertices of ``canonical`` (V, 3) with a
    margin that holds the exterior's whole room (a decided ``max_dist`` may exceed ``nerf_margin``)."""
    return _box(canonical[region], room_margin(nerf_margin, max_dist))


class HybridAvatar(nn.Module):
    def __init__(self, body: BodyModel, spec: AvatarSpec, init: InitParams, skin_color: torch.Tensor,
                 background: torch.Tensor, resolution: int, frame_time: Optional[torch.Tensor] = None,
                 framed: Optional[torch.Tensor] = None):  # fmt: skip
        """``framed``: (V,) bool, the vertices the capture frames (:func:`delta.scene.framing.framed_vertices`);
        the fields' boxes hold the modelled vertices among them (None: every modelled vertex)."""
        super().__init__()
        self.body, self.spec, self.resolution = body, spec, resolution
        self.register_buffer("background", background.float().clone())
        self.betas = nn.Parameter(init.betas.float().clone())
        self.poses = nn.Parameter(init.poses.float().clone())
        self.transl = nn.Parameter(init.transl.float().clone())
        self.expression = None
        if init.expression is not None:  # a tracked face: its expressions are refined with the pose
            if body.num_expression < init.expression.shape[1]:
                raise ValueError(f"the init has {init.expression.shape[1]} expression coefficients, the body model "
                                 f"'{body.name}' {body.num_expression}")  # fmt: skip
            self.expression = nn.Parameter(init.expression.float().clone())
        self.pinhole = isinstance(init.camera, PinholeCamera)
        if self.pinhole:
            cam = init.camera
            for k in ("K", "R", "t"):
                self.register_buffer(f"cam_{k}", getattr(cam, k).float().clone())
        else:
            self.ortho_scale = nn.Parameter(init.camera.scale.float().clone())
            self.ortho_trans = nn.Parameter(init.camera.trans.float().clone())
        template = body.v_template.float()
        self.register_buffer("edges", mesh_edges(body.faces))
        modelled = modelled_vertices(body, spec.capture).to(template.device)
        # (V,) bool: the vertices this capture models (derived from the body, not saved)
        self.register_buffer("modelled", modelled, persistent=False)
        ids = knn_vertex_ids(body, spec.render.knn_vertices).to(template.device)
        self.register_buffer("knn_ids", ids[modelled[ids]], persistent=False)
        pose_mask = torch.ones(body.num_joints, device=template.device)
        pose_mask[list(spec.frozen_joints)] = 0.0
        self.register_buffer("pose_mask", pose_mask, persistent=False)
        cano = lbs(body, torch.zeros(1, 1), body.canonical_pose[None].float())
        self.register_buffer("canonical_T", cano.vertex_transforms_3x4[0].clone())
        self.register_buffer("canonical_vertices", cano.vertices[0].clone())
        if framed is not None and tuple(framed.shape) != tuple(modelled.shape):
            raise ValueError(
                f"framed: {tuple(framed.shape)} vertices, the body model '{body.name}' has {len(modelled)}"
            )
        region = modelled if framed is None else modelled & framed.to(device=template.device, dtype=torch.bool)
        if not region.any():
            raise ValueError("the capture frames none of the modelled vertices (framed and modelled do not meet)")
        # (V,) bool: the vertices the fields' boxes hold (what the capture frames of what it models)
        self.register_buffer("framed", region, persistent=False)
        # without the framed vertices (a file from before them) the vertex fields' box is the whole template's
        tbox = _box(template if framed is None else template[region], 0.05)
        nv = body.num_vertices
        self.offset_field = VertexField(spec.offsets, tbox, "offset", spec.offset_scale, num_vertices=nv)
        self.albedo_field = VertexField(spec.albedo, tbox, "albedo", init=skin_color, num_vertices=nv,
                                        prior=mouth_prior(body, skin_color, spec.mouth_shade))  # fmt: skip
        # the albedo where no training frame looked (ids (U,), values (U, 3)): set after training from what the
        # frames saw (delta.models.unseen), saved beside the weights, none until then
        self.register_buffer("fill_ids", torch.zeros(0, dtype=torch.int64, device=template.device), persistent=False)
        self.register_buffer("fill_values", template.new_zeros(0, 3), persistent=False)
        # the exterior read at its mirror through the body where no training frame looked (delta.models.unseen)
        self.exterior_mirror = None
        nbox = exterior_box(self.canonical_vertices, region, spec.nerf_margin, spec.render.max_dist)
        self.nerf = None
        if spec.nerf is not None:
            part = bool((modelled & ~region).any())  # no exterior beyond the box around what is framed
            self.nerf = (LayeredNeRF(spec.nerf, nbox, tuple(spec.layers), bounded=part) if spec.layers
                         else NeRFField(spec.nerf, nbox, bounded=part))  # fmt: skip
        if spec.render.hair_carriage not in HAIR_CARRIAGES:
            raise ValueError(f"render.hair_carriage: '{spec.render.hair_carriage}' (expected one of "
                             f"{', '.join(HAIR_CARRIAGES)})")  # fmt: skip
        # (K,) bool over the kNN's vertices: the head's (derived from the body, not saved)
        self.register_buffer("head_carriers", head_vertices(body).to(self.knn_ids.device)[self.knn_ids],
                             persistent=False)  # fmt: skip
        # (low, high) canonical heights of the shoulders' and the head's joints (None: the body has not both)
        self._head_span = hair_span(body, cano.joints[0])
        if spec.render.hair_carriage == "height" and self._head_span is None:
            raise ValueError(f"render.hair_carriage: 'height' needs a head joint and shoulders; the body "
                             f"model '{body.name}' lacks one of them")  # fmt: skip
        if spec.clothing_off_head and "clothing" in spec.layers and self.nerf is not None:
            # the head's vertices carry no clothing (backward skinning's nearest vertex of a point)
            self.nerf.layers["clothing"].barred_carriers = self.head_carriers
        self.deformation = None
        if spec.deformation is not None:
            self.deformation = DeformationField(spec.deformation, nbox, spec.deformation_scale,
                                                time_freqs=spec.time_freqs)  # fmt: skip
        n = len(init.poses)
        tau = frame_time.float() if frame_time is not None else torch.full((n,), float("nan"))
        if tau.shape != (n,):
            raise ValueError(f"frame_time: shape {tuple(tau.shape)}, expected ({n},)")
        # normalised time of each frame (NaN: outside the training sequence); derived from the
        # record, not saved, so stage-1 checkpoints load into stage 2 unchanged
        self.register_buffer("frame_time", tau.to(template.device), persistent=False)
        self.trajectory = Trajectory(self.frame_time, spec.pose_knots) if spec.pose_knots else None
        occ = spec.render.occupancy
        self.occupancy = None
        if self.nerf is not None and occ.enabled:
            dilation = spec.deformation_scale if self.deformation is not None else 0.0
            self.occupancy = OccupancyGrid(nbox, occ, dilation, body=self.canonical_vertices[region])

    def _apply(self, fn, recurse: bool = True):
        """``.to(device)`` and friends also move the body model (a dataclass, not a module)."""
        out = super()._apply(fn, recurse)
        self.body = self.body.to(device=self.background.device)
        return out

    # ------------------------------------------------------------ parts
    def camera(self, frame: int):
        n = self.resolution
        if self.pinhole:
            return PinholeCamera(self.cam_K, self.cam_R, self.cam_t, None, n, n)  # frames undistorted: an ideal lens
        scale, trans = self.ortho_scale[frame], self.ortho_trans[frame]
        if self.trajectory is not None:
            shift = self.trajectory(frame)[1]
            scale, trans = scale * shift[0].exp(), trans + shift[1:]
        return OrthographicCamera(scale, trans, n, n)

    def offsets(self) -> torch.Tensor:
        """(V, 3) canonical offsets F_d(t)."""
        return self.offset_field(self.body.v_template)

    def albedo(self) -> torch.Tensor:
        """(V, 3) vertex albedo F_t(t), the fill where no training frame looked (:meth:`fill_albedo`) in its place."""
        albedo = self.albedo_field(self.body.v_template)
        if len(self.fill_ids):
            albedo = albedo.index_put((self.fill_ids,), self.fill_values.to(albedo.dtype))
        return albedo

    def fill_albedo(self, ids: torch.Tensor, values: torch.Tensor) -> None:
        """Replace the albedo of vertices ``ids`` (U,) by ``values`` (U, 3) (what the field holds where no
        training frame looked; ``delta.models.unseen``); empty ``ids``: the field everywhere."""
        ids = torch.as_tensor(ids, dtype=torch.int64)
        values = torch.as_tensor(values, dtype=torch.float32).reshape(-1, 3)
        n = self.body.num_vertices
        if len(ids) != len(values) or (len(ids) and (int(ids.min()) < 0 or int(ids.max()) >= n)):
            raise ValueError(f"albedo fill: {len(ids)} ids in [0, {n}) for {len(values)} values expected")
        self.fill_ids = ids.to(self.fill_ids.device)
        self.fill_values = values.to(self.fill_values.device)

    def pose_body(self, frame: int, offsets: Optional[torch.Tensor] = None):
        """LBS output of one frame (batch of 1)."""
        expression = None if self.expression is None else self.expression[frame : frame + 1]
        if self.trajectory is None:
            return lbs(self.body, self.betas[None], self.poses[frame : frame + 1], expression, offsets=offsets,
                       transl=self.transl[frame : frame + 1])  # fmt: skip
        frames = torch.tensor([frame], device=self.poses.device)
        rot, transl = self._corrected(batch_rodrigues(self.poses[frames]), self.transl[frames], frames)
        return lbs(self.body, self.betas[None], rot, expression, offsets=offsets, transl=transl, pose_is_rotmat=True)

    def _corrected(self, rot: torch.Tensor, transl: torch.Tensor, frames: torch.Tensor):
        """(B, J, 3, 3) rotations and (B, 3) translations of ``frames`` (B,) with the trajectory's correction:
        its turn before the root's own rotation, its shift added to a pinhole camera's translation."""
        turn, shift = self.trajectory(frames)
        rot = torch.cat([(batch_rodrigues(turn) @ rot[:, 0])[:, None], rot[:, 1:]], 1)
        return rot, transl + shift if self.pinhole else transl

    def local_rotations(self, frames: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The (B, J, 3, 3) local joint rotations and (B, 3) translations of ``frames`` (B,) (None: every
        frame), with the trajectory's correction (what :meth:`pose_body` poses)."""
        if frames is None:
            frames = torch.arange(self.poses.shape[0], device=self.poses.device)
        rot = batch_rodrigues(self.poses[frames])
        if self.trajectory is None:
            return rot, self.transl[frames]
        return self._corrected(rot, self.transl[frames], frames)

    def skeletons(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Every frame's (F, 3, 3) root rotation and (F, J, 3) posed joints, without skinning a vertex."""
        rot, transl = self.local_rotations()
        return rot[:, 0], posed_joints(self.body, self.betas, rot, transl)

    def posed_mesh(self, frame: int) -> tuple[PosedMesh, torch.Tensor, torch.Tensor]:
        """The posed interior of one frame, with the offsets and posed vertices for the regularisers."""
        offsets = self.offsets()
        out = self.pose_body(frame, offsets)
        verts = out.vertices[0]
        uv, _ = self.camera(frame).project(verts)
        skinning = None
        if self.nerf is not None:
            ids = self.knn_ids
            disp = out.rest_vertices[0, ids] - self.body.v_template[ids]
            rs = self.spec.render
            # a distance grid pays only for culling near the body; with max_dist beyond GRID_REACH (no
            # culling, the paper's setting) it would cover metres of empty space: the KD-tree answers
            cell = rs.probe_cell if rs.max_dist <= GRID_REACH else 0.0
            skinning = deformer.prepare(
                verts[ids],
                out.vertex_transforms_3x4[0, ids],
                disp,
                self.canonical_T[ids],
                self.body.weights[ids],
                cell,
                rs.max_dist + 2 * rs.probe_cell,
                rs.contact_cell,
                self._round_trip_grid() if rs.round_trip and cell > 0 else None,
                self.hair_carriers,
                self.hair_span,
            )
        mesh = PosedMesh(verts, self.body.faces, self.albedo(), uv, skinning, self.exterior_mirror)
        return mesh, offsets, out

    def _round_trip_grid(self):
        """The kNN vertices' canonical positions on a grid (frame-independent: built once per body and device)."""
        ids, rs = self.knn_ids, self.spec.render
        # a body or transforms replaced (another device, another body) are other tensors: another grid
        key = (str(ids.device), len(ids), rs.probe_cell, rs.max_dist, self.canonical_T.data_ptr(),
               self.body.v_template.data_ptr())  # fmt: skip
        cached = getattr(self, "_round_trip_cache", None)
        if cached is None or cached[0] != key:
            T, v = self.canonical_T[ids], self.body.v_template[ids].to(self.canonical_T.dtype)
            canonical = (T[..., :3] @ v[..., None]).squeeze(-1) + T[..., 3]
            grid = deformer.canonical_grid(canonical, rs.probe_cell, rs.max_dist + 2 * rs.probe_cell)
            self._round_trip_cache = cached = (key, grid)
        return cached[1]

    @property
    def hair_carriers(self) -> Optional[torch.Tensor]:
        """(K,) bool over the kNN's vertices: the head's, which carry a hair layer bound to the head
        (``render.hair_carriage``: ``head`` or ``height``); None where the hair is not bound (or there is no
        hair layer).
        Read from the spec, so an exterior worn from another avatar carries its hair as that one did."""
        if self.spec.render.hair_carriage == "nearest" or "hair" not in self.spec.layers or self.nerf is None:
            return None
        return self.head_carriers

    @property
    def hair_span(self) -> Optional[tuple[float, float]]:
        """(low, high): the canonical heights of the shoulders and the head's joint, over which a hair layer
        carried by height (``render.hair_carriage: height``) passes from the body's carriage to the head's;
        None for another carriage (or no hair layer). Read from the spec, as :attr:`hair_carriers` is."""
        if self.spec.render.hair_carriage != "height" or self.hair_carriers is None:
            return None
        return self._head_span

    def time_code(self, frame: int) -> Optional[torch.Tensor]:
        """F_e's time input for a frame (zeros outside the training sequence); None without one."""
        if self.deformation is None or not self.spec.time_freqs:
            return None
        return time_features(self.frame_time[frame], self.spec.time_freqs)

    def _exterior_reads(self, frame: int, timeless: bool = False):
        """The occupancy test (None while the grid is not in use) and F_e at the frame's time (without it where
        ``timeless``; None without F_e) that a frame's rays read the exterior through."""
        occ = self.occupancy
        occupied = occ.contains if occ is not None and bool(occ.active) else None
        code = None if timeless else self.time_code(frame)
        nonrigid = self.deformation if code is None else functools.partial(self.deformation, time=code)
        return occupied, nonrigid

    def render(self, frame: int, pixels: torch.Tensor, generator: torch.Generator | None = None,
               mesh: Optional[PosedMesh] = None, timeless: bool = False, through_mesh: bool = False,
               soft: bool = True) -> RayRender:  # fmt: skip
        """Render pixel centres (R, 2) of a frame (``timeless``: F_e without the frame's time;
        ``through_mesh``: the NeRF alone, rays not stopping at the mesh; ``soft`` False: the hits as
        the silhouette)."""
        if mesh is None:
            mesh = self.posed_mesh(frame)[0]
        origins, dirs = self.camera(frame).rays(pixels)
        occupied, nonrigid = self._exterior_reads(frame, timeless)
        return render_rays(mesh, origins, dirs, pixels, self.background, self.spec.render, self.nerf,
                           nonrigid, generator, occupied, through_mesh, soft)  # fmt: skip

    def canonical_points(self, frame: int, pixels: torch.Tensor, generator: torch.Generator | None = None,
                         timeless: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
        """Where rays through pixels (R, 2) of a frame see the exterior, taken to the canonical space (R, 3),
        the rays' directions there (R, 3, unit: by the linear part of the map of the point's nearest vertex)
        and the opacity of the exterior (R,), 0 where that point is beyond the body's reach.

        The posed point is the rays' opacity-weighted depth (:func:`delta.render.hybrid.exterior_surface`,
        not differentiated); it goes back by the frame's kNN maps and F_e, differentiable in F_e alone (the
        frame's pose and camera held): what registers the same point of the cloth across frames."""
        if self.nerf is None:
            raise ValueError("canonical_points: the avatar has no exterior")
        rs = self.spec.render
        occupied, nonrigid = self._exterior_reads(frame, timeless)
        with torch.no_grad():
            mesh = self.posed_mesh(frame)[0]
            origins, dirs = self.camera(frame).rays(pixels)
            surface, opacity = exterior_surface(mesh, origins, dirs, rs, self.nerf, nonrigid, generator, occupied)
        d = deformer.deform(mesh.skinning, surface, rs.k, rs.sigma, rs.max_dist)
        points = d.canonical if nonrigid is None else d.canonical + nonrigid(d.canonical, d.posed_ref)
        linear = mesh.skinning.to_canonical[d.nearest, :, :3]
        along = torch.nn.functional.normalize((linear @ dirs[:, :, None]).squeeze(-1), dim=-1)
        return points, along, opacity * d.valid

    def update_occupancy(self, seed: int, early: bool = False) -> None:
        """Re-evaluate the occupancy grid's densities (a training step calls this every few steps;
        ``early``: before the warm-up's end, the body's shell of cells kept)."""
        self.occupancy.update(self.nerf.density, seed, early=early)

    def mask_frozen_pose_gradient(self) -> None:
        """Zero the pose gradient of frozen joints: Adam then never moves them (exactly)."""
        if self.poses.grad is not None and self.spec.frozen_joints:
            self.poses.grad.mul_(self.pose_mask[None, :, None])

    def per_frame_parameters(self) -> list[torch.Tensor]:
        """Parameters with one slice per frame (pose, translation, expression, orthographic camera)."""
        face = [] if self.expression is None else [self.expression]
        return [self.poses, self.transl] + face + ([] if self.pinhole else [self.ortho_scale, self.ortho_trans])

    def param_groups(self, lr: dict) -> list[dict]:
        """Optimiser groups, each ``name``d: networks, shape, per-frame pose, per-frame camera (lr keys: fields,
        nerf, deformation (default: nerf's), pose, camera, shape, trajectory)."""
        groups = [
            {
                "params": list(self.offset_field.parameters()) + list(self.albedo_field.parameters()),
                "lr": lr["fields"],
                "name": "fields",
            },
            {"params": [self.betas], "lr": lr["shape"], "name": "shape"},
            {
                "params": [self.poses, self.transl] + ([] if self.expression is None else [self.expression]),
                "lr": lr["pose"],
                "name": "pose",
            },  # fmt: skip
        ]
        if self.nerf is not None:
            groups.append({"params": list(self.nerf.parameters()), "lr": lr["nerf"], "name": "nerf"})
        if self.deformation is not None:
            rate = lr.get("deformation", lr["nerf"])
            groups.append({"params": list(self.deformation.parameters()), "lr": rate, "name": "deformation"})
        if not self.pinhole:
            groups.append({"params": [self.ortho_scale, self.ortho_trans], "lr": lr["camera"], "name": "camera"})
        if self.trajectory is not None:
            groups.append({"params": list(self.trajectory.parameters()), "lr": lr["trajectory"], "name": "trajectory"})
        return groups
