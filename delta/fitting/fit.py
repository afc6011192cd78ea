"""Staged, batched fitting of shared shape, per-frame pose and camera to 2D keypoints and person masks.

Stage 1 fits the global orientation and translation (pinhole) or the per-frame
scaled-orthographic camera to the torso keypoints, from several headings a frame
(the best-fitting one is kept: a subject facing away is not a mirror image); stage 2 adds the body pose
with its priors (per-joint pose prior, knee bend prior, joint-angle limits);
stage 3 adds the shared shape, temporal smoothness and, when masks are given,
the silhouette of a coarse body mesh; midway through it, a free frame that costs clearly more than a
neighbour costs on its own frame is refitted from their poses too and takes one where clearly cheaper
(``neighbour_reach``: a local minimum its neighbours escaped). Frames with too few confident keypoints
or an empty mask are flagged and take their neighbours' parameters. All frames
are optimised together (no per-frame Python loop). With a ``FitStart`` (body
parameters a dataset provides for the same model) only stage 3 runs, from them.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from delta.body.keypoints import KeypointMap
from delta.body.lbs import batch_rodrigues, rigid_transforms, skin
from delta.body.model import BodyModel
from delta.body.rotations import matrix_to_axis_angle
from delta.cameras.models import OrthographicCamera, PinholeCamera
from delta.fitting import silhouette as sil
from delta.fitting import terms
from delta.fitting.limits import forward_directions, joint_limits
from delta.fitting.settings import FitConfig
from delta.fitting.visibility import LIMB_ENDS, SEEN, hidden_seen
from delta.fitting.start import FACE, TORSO, facing_orientation, init_ortho_scale, init_translation, interpolate
from delta.optim import Adam
from delta.progress import Progress


#: OpenPose-18 bones whose extent along the viewing axis the depth term compares: the head, shoulders and hips
#: from the neck, and the limbs
DEPTH_BONES = ((1, 0), (1, 2), (2, 3), (3, 4), (1, 5), (5, 6), (6, 7), (1, 8), (8, 9), (9, 10), (1, 11), (11, 12),
               (12, 13))  # fmt: skip
#: and across the torso: right to left hip (the pelvis's turn; the shoulders' order, wrong beyond 5 cm in 4 of
#: loose's frames, cost more than it gained)
DEPTH_PAIRS = ((8, 11),)


@dataclasses.dataclass
class FitStart:
    """Body parameters to start from (a dataset's, for the same body model)."""

    betas: torch.Tensor
    """(S,) shape."""
    pose: torch.Tensor
    """(F, J, 3) axis-angle pose."""
    transl: torch.Tensor
    """(F, 3) translation (ignored with an orthographic camera, whose template then carries the cameras)."""


@dataclasses.dataclass
class FitResult:
    betas: torch.Tensor
    """(S,) shared shape."""
    pose: torch.Tensor
    """(F, J, 3) axis-angle pose (joint 0 is the global orientation)."""
    transl: torch.Tensor
    """(F, 3) body translation (zero for orthographic cameras)."""
    camera: object
    """The fitted camera: the given pinhole, or an OrthographicCamera with (F,) scale and (F, 2) translation."""
    flagged: torch.Tensor
    """(F,) bool: too few keypoints or an empty mask; parameters interpolated from neighbours."""
    few_keypoints: torch.Tensor
    """(F,) bool: fewer than ``min_keypoints`` confident keypoints."""
    empty_mask: torch.Tensor
    """(F,) bool: the person mask is empty (all False without masks)."""
    residual_px: torch.Tensor
    """(F,) mean reprojection error over confident keypoints (nan when flagged)."""
    neighbour_starts: list[tuple[int, int]] = dataclasses.field(default_factory=list)
    """(frame, the frame whose pose it took) for each swap of the sweeps of neighbour starts, in order."""
    neighbour_refits: list[int] = dataclasses.field(default_factory=list)
    """The frames the sweeps refitted from their neighbours' poses (a neighbour cost less), in order."""


class PosedPoints:
    """3D keypoints (and optionally a vertex subset) of a body model, skinning only the vertices needed."""

    def __init__(self, model: BodyModel, kp_map: KeypointMap, extra_vids: torch.Tensor | None = None):
        self.model = model
        kp_vids = torch.nonzero(kp_map.vertex_weights.abs().sum(0) > 0).squeeze(1)
        self.n_extra = 0 if extra_vids is None else len(extra_vids)
        self.vids = kp_vids if extra_vids is None else torch.cat([extra_vids, kp_vids])
        self.vw = kp_map.vertex_weights[:, kp_vids].to(model.v_template.dtype)
        self.jw = kp_map.joint_weights.to(model.v_template.dtype)

    def __call__(self, betas, pose, transl) -> tuple[torch.Tensor, torch.Tensor]:
        """(S,), (F, J, 3), (F, 3) -> (F, K, 3) keypoints and (F, V_extra, 3) extra vertices."""
        m, F, S = self.model, pose.shape[0], betas.shape[0]
        joints = m.joints_template + torch.einsum("s,jcs->jc", betas, m.joints_shapedirs[..., :S])
        verts = m.v_template[self.vids] + torch.einsum("s,vcs->vc", betas, m.shapedirs[self.vids][..., :S])
        posed_joints, A = rigid_transforms(batch_rodrigues(pose), joints.expand(F, -1, -1), m.parents)
        posed, _ = skin(verts.expand(F, -1, -1), m.weights[self.vids], A)
        posed = posed + transl[:, None]
        kp = torch.einsum("kj,fjc->fkc", self.jw, posed_joints + transl[:, None])
        kp = kp + torch.einsum("kv,fvc->fkc", self.vw, posed[:, self.n_extra :])
        return kp, posed[:, : self.n_extra]


class KeypointModel(PosedPoints):
    """3D keypoints only: (S,), (F, J, 3), (F, 3) -> (F, K, 3)."""

    def __call__(self, betas, pose, transl) -> torch.Tensor:
        return super().__call__(betas, pose, transl)[0]


def unobserved_projectors(kp_model: KeypointModel, num_shape: int, num_joints: int, tol: float = 1e-6) -> torch.Tensor:
    """(J, 3, 3) projectors onto each joint's rotations that move no keypoint, at the rest pose and mean shape.

    Joint j's block of the keypoints' Jacobian with respect to its axis-angle gives a 3 x 3 Gram matrix;
    its eigenvectors with eigenvalues below ``tol`` times the largest of any joint span what the
    keypoints cannot see: all three axes of a wrist, a foot or a finger (OpenPose-18 has no point
    beyond them), the twist of a straight limb about its bone. The root is left out (0).
    """
    betas = torch.zeros(num_shape, dtype=torch.float64)
    transl = torch.zeros(1, 3, dtype=torch.float64)
    rest = torch.zeros(1, num_joints, 3, dtype=torch.float64)
    # many keypoints (a face fit's 432): one batched backward pass (vmap) instead of one a coordinate, the same
    # numbers in 2.0 s instead of 7.4 (one thread); for OpenPose-18 the plain passes are faster (0.3 against 0.9 s)
    many = kp_model.jw.shape[0] > num_joints
    jac = torch.autograd.functional.jacobian(lambda p: kp_model(betas, p, transl), rest, vectorize=many)
    # (1, K, 3, 1, J, 3)
    blocks = jac.reshape(-1, num_joints, 3).permute(1, 0, 2)  # (J, 3K, 3)
    gram = blocks.transpose(1, 2) @ blocks  # (J, 3, 3)
    vals, vecs = torch.linalg.eigh(gram)
    blind = (vals < tol * vals.max()).to(torch.float64)  # (J, 3)
    proj = vecs @ torch.diag_embed(blind) @ vecs.transpose(1, 2)
    proj[0] = 0.0
    return proj


def _project(camera, pinhole: bool, cam_params: list[torch.Tensor], points: torch.Tensor) -> torch.Tensor:
    if pinhole:
        return camera.project(points)[0]
    return OrthographicCamera(cam_params[0].exp(), cam_params[1], camera.width, camera.height).project(points)[0]


#: optimisation steps between progress lines
PROGRESS_EVERY = 50


def fit(model: BodyModel, kp_map: KeypointMap, detected: torch.Tensor, camera, cfg: FitConfig = FitConfig(),
        pose_weights: torch.Tensor | None = None, knees: list[int] = (), masks: torch.Tensor | None = None,
        start: FitStart | None = None, exterior: torch.Tensor | None = None,
        sequence: torch.Tensor | None = None, depth: torch.Tensor | None = None,
        held_joints: torch.Tensor | None = None, held_frames: torch.Tensor | None = None,
        tied: bool = False) -> FitResult:  # fmt: skip
    """Fit β, θ_f and the camera to (F, 18, 3) keypoint detections and optional (F, H, W) person masks.

    ``exterior`` (F, H, W), the part of the person masks that is clothing or hair, gets the
    ``cfg.exterior_fill`` weight when the body leaves it uncovered.

    ``sequence`` (F,) labels the sequence each frame belongs to (consecutive frames of different
    labels are not tied by the temporal terms; ``cfg.static_weight`` holds label 0's pose); None: one sequence.

    ``held_joints`` (J,) bool: the joints ``cfg.static_weight`` holds near their mean (default: every joint
    but the root). ``held_frames`` (F,) bool: the frames held (default: those of label 0). ``tied``: the held
    joints are one value the held frames share, not pulled toward their mean, and with the root among them
    so is the translation (a still torso).

    ``depth`` (F, 18) holds a detector's relative depths of the first 18 keypoints (metres; non-finite:
    none), compared bone by bone with ``cfg.depth_weight``.

    ``camera`` is a PinholeCamera (static; the body moves) or an OrthographicCamera whose per-frame
    scale and translation are fitted (its own values are the start when ``start`` is given).
    """
    model = model.to(dtype=torch.float64)
    detected = torch.nan_to_num(detected.to(torch.float64), nan=0.0).clone()
    detected[..., 2] = torch.where(detected[..., 2] >= cfg.conf_threshold, detected[..., 2], 0.0)
    F, J = detected.shape[0], model.num_joints
    few = (detected[..., 2] > 0).sum(-1) < cfg.min_keypoints
    use_sil = masks is not None and cfg.sil_weight > 0
    small = sil.downsample_masks(masks, cfg.sil_size) if masks is not None else None
    empty = small.flatten(1).amax(-1) <= 0 if small is not None else torch.zeros(F, dtype=torch.bool)
    outer = sil.downsample_masks(exterior, cfg.sil_size) if use_sil and exterior is not None else None
    fill = sil.fill_weights(outer, cfg.sil_fill, cfg.exterior_fill)
    skin_scale = sil.skin_edge_scale(small, outer, cfg.skin_edge_weight) if use_sil else 1.0
    flagged = few | empty
    detected[flagged, :, 2] = 0.0
    coarse = sil.coarse_mesh(model, cfg.sil_cell) if use_sil else None
    points = PosedPoints(model, kp_map, coarse.vertex_ids if use_sil else None)
    pose_weights = torch.ones(J, dtype=torch.float64) if pose_weights is None else pose_weights
    kp_model = KeypointModel(model, kp_map)
    blind = unobserved_projectors(kp_model, model.num_shape, J) if cfg.unobserved_weight > 0 else None
    pinhole = isinstance(camera, PinholeCamera)
    if start is not None:
        betas = start.betas.to(torch.float64).clone()
        pose = start.pose.to(torch.float64).clone()
        transl = start.transl.to(torch.float64).clone() if pinhole else torch.zeros(F, 3, dtype=torch.float64)
    else:
        betas = torch.zeros(model.num_shape, dtype=torch.float64)
        pose = torch.zeros(F, J, 3, dtype=torch.float64)
        pose[:, 0] = facing_orientation(camera)
        kp0 = points(betas, pose, torch.zeros(F, 3, dtype=torch.float64))[0].detach()
        transl = init_translation(kp0, detected, camera) if pinhole else torch.zeros(F, 3, dtype=torch.float64)
    cam_params: list[torch.Tensor] = []
    if not pinhole:
        if start is not None:
            log_scale = torch.as_tensor(camera.scale, dtype=torch.float64).expand(F).log().clone()
            trans = torch.as_tensor(camera.trans, dtype=torch.float64).expand(F, 2).clone()
        else:
            log_scale = init_ortho_scale(kp0, detected, camera.height).log()
            trans = torch.zeros(F, 2, dtype=torch.float64)
        cam_params = [log_scale.requires_grad_(), trans.requires_grad_()]
    use_depth = depth is not None and cfg.depth_weight > 0
    if use_depth:
        depth = depth.to(torch.float64)
        depth = torch.cat([depth, depth.new_full((F, detected.shape[1] - depth.shape[1]), torch.nan)], 1)
        bones, pairs = torch.tensor(DEPTH_BONES), torch.tensor(DEPTH_PAIRS)
    if start is None and cfg.iterations[0] > 0:
        _best_heading(kp_model, camera, pinhole, detected, betas, pose, transl, cam_params, cfg,
                      depth if use_depth else None)  # fmt: skip
    prior = PosePrior(cfg, pose_weights, list(knees), *joint_limits(model), blind)
    starts = limb_starts(model, cfg.forward_start)
    limbs_done = start is None and cfg.iterations[1] > 0 and len(starts) > 1
    if limbs_done:
        mesh = coarse if coarse is not None else sil.coarse_mesh(model, cfg.sil_cell)
        seen_by = PosedPoints(model, kp_map, mesh.vertex_ids), torch.as_tensor(mesh.faces), camera
        ends = torch.tensor([n in LIMB_ENDS for n in kp_map.names])
        _limbs_by_visibility(points, seen_by, pinhole, detected, ends, betas, pose, transl, cam_params, cfg, prior,
                             starts)  # fmt: skip
    for t in (betas, pose, transl):
        t.requires_grad_()
    image_size = (camera.width, camera.height)
    sil_w = (~empty).to(torch.float64)
    seq = None if sequence is None else torch.as_tensor(sequence)
    links = None if seq is None else seq[1:] == seq[:-1]
    held = held_frames.to(torch.bool) if held_frames is not None else None if seq is None else seq == 0
    if held_joints is None:
        held_joints = torch.arange(J) > 0
    held_joints = held_joints.to(torch.bool)

    every = torch.arange(F)
    tie = (lambda: tie_held(pose, transl, held, held_joints)) if tied and cfg.static_weight > 0 else (lambda: None)
    tie()

    def frame_cost(P: torch.Tensor, tr: torch.Tensor, cams: list[torch.Tensor], rows: torch.Tensor,
                   stage: int) -> torch.Tensor:  # fmt: skip
        """(N,) each problem's own cost (keypoints, pose priors, depth; silhouette in stage 3) for the
        (N, J, 3) poses, (N, 3) translations and (N, ...) cameras of the frames ``rows`` (N,)."""
        kp3d, verts = points(betas, P, tr)
        det = detected[rows]
        cost = terms.keypoint_term(_project(camera, pinhole, cams, kp3d), det, cfg.sigma_px) + prior(P)
        if use_depth:
            along = camera.project(kp3d)[1]  # depth along the viewing axis (an orthographic camera's too)
            limbs = terms.depth_term(along, depth[rows], det[..., 2], bones, cfg.depth_sigma, cfg.depth_margin)
            turn = terms.depth_term(along, depth[rows], det[..., 2], pairs, cfg.depth_sigma, cfg.depth_pair_margin)
            cost = cost + cfg.depth_weight * cfg.sigma_px**2 * (limbs + turn)
        if stage > 1 and use_sil:
            uv = _project(camera, pinhole, cams, verts)
            rendered = sil.frames_silhouette(uv, coarse.faces, cfg.sil_size, image_size, cfg.sil_sigma,
                                             masks=small[rows], supersample=cfg.sil_supersample)  # fmt: skip
            weights, scale = (w[rows] if torch.is_tensor(w) else w for w in (fill, skin_scale))
            cost = cost + cfg.sil_weight * sil_w[rows] * sil.silhouette_term(rendered, small[rows], weights, scale)
        return cost

    def loss(stage: int) -> torch.Tensor:
        # stages 2 and 3 (stage 1 is _best_heading)
        total = frame_cost(pose, transl, cam_params, every, stage).sum()
        if stage > 1:
            total = total + cfg.shape_weight * terms.shape_prior(betas) * F * cfg.sigma_px
            smooth = terms.rotation_smoothness(pose[:, 0], links) + terms.smoothness(pose[:, 1:], links)
            smooth = smooth + terms.smoothness(transl, links)
            total = total + cfg.smooth_weight * cfg.sigma_px * smooth
            if cfg.accel_weight > 0:
                accel = terms.rotation_acceleration(pose[:, 0], links) + terms.acceleration(pose[:, 1:], links)
                accel = accel + terms.acceleration(transl, links)
                accel = accel + sum(terms.acceleration(c, links) for c in cam_params)
                total = total + cfg.accel_weight * cfg.sigma_px * accel
            if cfg.static_weight > 0 and not tied:  # tied, the held frames share one value: no spread to weigh
                total = total + cfg.static_weight * cfg.sigma_px * terms.static_pose(pose[:, held_joints], held)
        return total

    stages = list(enumerate(cfg.iterations))
    todo = stages[2:] if start is not None or limbs_done else stages[1:]
    free = ~held if held is not None and cfg.static_weight > 0 else torch.ones(F, dtype=torch.bool)
    movable = free & ~flagged
    rows, sources = neighbour_sources(movable, links, cfg.neighbour_reach)
    sweeps = cfg.neighbour_sweeps if len(rows) > int(movable.sum()) and todo else 0
    # the sweeps of neighbour starts, evenly spaced through the last stage (its optimiser goes on after each)
    last = todo[-1][1] if todo else 0
    sweep_at = {round(last * k / (sweeps + 1)) for k in range(1, sweeps + 1)} if sweeps else set()
    progress = Progress(f"fit ({pose.shape[0]} frames)", sum(steps for _, steps in todo) + sweeps * cfg.neighbour_steps)
    done, swaps, refits = 0, [], []
    for i, (stage, steps) in enumerate(todo):
        params = [transl] * pinhole + cam_params + [pose] + [betas] * (stage > 1)
        # steps scale with the body's distance: what moves a far body a little throws a close-up's face off
        scale = distance_scale(camera, points(betas, pose, transl)[0]) if pinhole else 1.0
        opt = Adam(params, lr=cfg.lr * scale)
        for step in range(steps):
            if i == len(todo) - 1 and step in sweep_at:
                swapped, refitted = _keep_cheapest(frame_cost, rows, sources, pose, transl, cam_params, pinhole,
                                                   stage, cfg.neighbour_steps, cfg.lr * scale)  # fmt: skip
                swaps, refits = swaps + swapped, refits + refitted
                done += cfg.neighbour_steps
                progress.report(done, "fit: neighbour starts")
            opt.zero_grad()
            value = loss(stage)
            value.backward()
            for p in params:  # a non-finite gradient (degenerate geometry) must not poison the parameters
                torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
            opt.step()
            tie()
            done += 1
            if done % PROGRESS_EVERY == 0 or done == progress.total:
                progress.report(done, f"fit stage {stage + 1}")
    res = _result(points, betas, pose, transl, camera, cam_params, detected, few, empty)
    res.neighbour_starts, res.neighbour_refits = swaps, refits
    return res


def tie_held(pose: torch.Tensor, transl: torch.Tensor, held: torch.Tensor | None, joints: torch.Tensor) -> None:
    """Give the ``held`` frames (None: all) one value of the held ``joints``' rotations (their mean; the
    held spread is small) and, with the root among them, of the translation."""
    rows = torch.arange(pose.shape[0]) if held is None else torch.nonzero(held).squeeze(1)
    if len(rows) < 2:
        return
    with torch.no_grad():
        sub = pose[rows][:, joints]
        pose[rows.unsqueeze(1), torch.nonzero(joints).squeeze(1)] = sub.mean(0, keepdim=True).expand_as(sub)
        if joints[0]:
            transl[rows] = transl[rows].mean(0, keepdim=True).expand(len(rows), -1)


#: the distance (m) at which the fit steps at ``FitConfig.lr``; a nearer body takes proportionally smaller steps
REFERENCE_DISTANCE = 3.0


def distance_scale(camera, keypoints: torch.Tensor) -> float:
    """The median camera depth of (F, K, 3) posed keypoints over ``REFERENCE_DISTANCE``, within [0.02, 1]."""
    with torch.no_grad():
        depth = camera.project(keypoints.detach().reshape(-1, 3))[1]
    return float((depth.median() / REFERENCE_DISTANCE).clamp(0.02, 1.0))


def neighbour_sources(free: torch.Tensor, links: torch.Tensor | None, reach: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,) frames and (N,) the frames whose pose each of them starts from in a sweep of neighbour starts:
    every ``free`` (F,) frame from its own pose and from those of the free frames up to ``reach`` before and
    after it in its sequence (``links`` (F-1,): frame i and i+1 are one sequence; None: all are), own first."""
    F = free.shape[0]
    same = torch.ones(max(F - 1, 0), dtype=torch.bool) if links is None else links.to(torch.bool)
    # run[i]: index of frame i's sequence, so that two frames are neighbours only within one
    run = torch.cat([torch.zeros(1, dtype=torch.long), (~same).long().cumsum(0)]) if F else torch.zeros(0)
    rows, sources = [torch.nonzero(free).squeeze(1)], [torch.nonzero(free).squeeze(1)]
    for offset in [o for r in range(1, reach + 1) for o in (-r, r)]:
        frame = torch.arange(F)
        other = frame + offset
        inside = (other >= 0) & (other < F)
        ok = free & inside
        ok[inside] &= free[other[inside]] & (run[other[inside]] == run[inside])
        rows.append(frame[ok])
        sources.append(other[ok])
    return torch.cat(rows), torch.cat(sources)


#: how much more a frame's own pose must cost than a neighbour's for the neighbour's to replace it: a fraction of
#: its own cost, and at least ``KEEP_FLOOR`` (the keypoint term costs about a keypoint's squared pixel error, so
#: 0.25 is half a pixel; where every copy fits to a rounding, as noiseless keypoints allow, none is swapped)
KEEP_MARGIN = 0.2
KEEP_FLOOR = 0.25


def worse_by_margin(cost: torch.Tensor, than: torch.Tensor) -> torch.Tensor:
    """Where ``cost`` exceeds a finite ``than`` by ``KEEP_MARGIN`` of itself, at least ``KEEP_FLOOR`` (a
    non-finite ``cost`` exceeds any finite ``than``)."""
    margin = torch.where(cost.isfinite(), KEEP_MARGIN * cost, 0.0).clamp_min(KEEP_FLOOR)
    return than.isfinite() & (cost - margin > than)


@torch.no_grad()  # the copies' own fits enable it
def _keep_cheapest(frame_cost, rows: torch.Tensor, sources: torch.Tensor, pose: torch.Tensor, transl: torch.Tensor,
                   cam_params: list[torch.Tensor], pinhole: bool, stage: int, steps: int,
                   lr: float) -> tuple[list[tuple[int, int]], list[int]]:  # fmt: skip
    """In place: where a frame of ``rows`` (N,) costs ``worse_by_margin`` than one of its ``sources`` (N,)
    costs on its own frame (a local minimum its neighbour escaped: an arm folded the wrong way), the poses of
    its sources (its own among them) given to it with its own translation and camera, each copy fitted
    ``steps`` steps to its frame alone (``frame_cost``), and the cheapest neighbour's copy taken where the
    frame's own copy, refitted alike, costs ``worse_by_margin`` than it. Every other frame keeps its pose as
    it was (copies of one basin end at costs a little apart, and a swap there only stirs the fit).
    Returns (frame, its pose's source) of each swap, and the frames refitted."""
    now = frame_cost(pose, transl, cam_params, torch.arange(pose.shape[0]), stage).nan_to_num(torch.inf)
    suspect = torch.zeros(pose.shape[0], dtype=torch.bool)
    suspect[rows[(rows != sources) & worse_by_margin(now[rows], now[sources])]] = True
    rows, sources = rows[suspect[rows]], sources[suspect[rows]]
    if len(rows) == 0:
        return [], []
    with torch.enable_grad():
        P = pose.detach()[sources].clone().requires_grad_()
        tr = transl.detach()[rows].clone().requires_grad_()
        cams = [c.detach()[rows].clone().requires_grad_() for c in cam_params]
        params = [tr] * pinhole + cams + [P]
        opt = Adam(params, lr=lr)
        # from the stage's rate down to a tenth of it: every copy settles before the costs are compared
        fall = 0.1 ** (1 / max(steps - 1, 1))
        for _ in range(steps):
            opt.zero_grad()
            frame_cost(P, tr, cams, rows, stage).sum().backward()
            for p in params:
                torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
            opt.step()
            for group in opt.param_groups:
                group["lr"] *= fall
    cost = frame_cost(P, tr, cams, rows, stage).nan_to_num(torch.inf)
    own = rows == sources
    own_cost = torch.full((pose.shape[0],), torch.inf, dtype=cost.dtype)
    own_cost[rows[own]] = cost[own]
    wins = torch.nonzero(~own & worse_by_margin(own_cost[rows], cost)).squeeze(1)
    order = wins[cost[wins].argsort()]
    order = order[rows[order].argsort(stable=True)]  # by frame, the cheapest first
    first = torch.ones_like(order, dtype=torch.bool)
    first[1:] = rows[order][1:] != rows[order][:-1]
    best = order[first]
    frames = rows[best]
    pose[frames] = P.detach()[best]
    if pinhole:
        transl[frames] = tr.detach()[best]
    for c, copies in zip(cam_params, cams):
        c[frames] = copies.detach()[best]
    return list(zip(frames.tolist(), sources[best].tolist())), torch.nonzero(suspect).squeeze(1).tolist()


def _copies(t: torch.Tensor, H: int) -> torch.Tensor:
    """(F * H, ...) leaf copies of (F, ...) per-frame values, each frame's H copies together."""
    return t.repeat_interleave(H, 0).detach().clone().requires_grad_()


@torch.no_grad()
def _keep(best: torch.Tensor, transl: torch.Tensor, cam_params: list[torch.Tensor], tr: torch.Tensor,
          cams: list[torch.Tensor]) -> None:  # fmt: skip
    """In place: each frame's translation and camera from the copy ``best`` (F,) indexes in ``tr`` and ``cams``."""
    transl.copy_(tr.detach()[best])
    for c, many_c in zip(cam_params, cams):
        c.data.copy_(many_c.detach()[best])


def _best_heading(
    kp_model: KeypointModel,
    camera,
    pinhole: bool,
    detected: torch.Tensor,
    betas: torch.Tensor,
    pose: torch.Tensor,
    transl: torch.Tensor,
    cam_params: list[torch.Tensor],
    cfg: FitConfig,
    depth: torch.Tensor | None = None,
) -> None:
    """Stage 1, in place: the global orientation and camera (or translation) fitted to the torso keypoints
    from ``cfg.facing_starts`` headings a frame at once (F x H problems in one batch); each frame keeps
    the heading whose torso and face keypoints (the face tells front from back and left from right
    turns) reproject best; the limbs, still at rest here, do not vote. With a detector's relative depths
    ``depth`` (F, K), the bones across the torso (``DEPTH_PAIRS``) vote too, as the later stages weigh
    them: a torso turned one way while the face looks the other reprojects almost alike at both turns."""
    F, H = pose.shape[0], max(cfg.facing_starts, 1)
    yaw = torch.arange(H, dtype=torch.float64) * (2 * math.pi / H)
    turn = batch_rodrigues(torch.stack([torch.zeros_like(yaw), yaw, torch.zeros_like(yaw)], -1))  # (H, 3, 3)
    rot = batch_rodrigues(pose[:, 0])[:, None] @ turn[None]  # (F, H, 3, 3): turned about the body's own up axis
    root = matrix_to_axis_angle(rot.reshape(F * H, 3, 3)).requires_grad_()
    rest = torch.zeros(F * H, pose.shape[1] - 1, 3, dtype=torch.float64)
    tr, cams = _copies(transl, H), [_copies(c, H) for c in cam_params]
    det = detected.repeat_interleave(H, 0)
    torso = det * _torso_mask(det)
    params = [root] + [tr] * pinhole + cams
    opt = Adam(params, lr=cfg.lr)
    for _ in range(cfg.iterations[0]):
        opt.zero_grad()
        kp = kp_model(betas, torch.cat([root[:, None], rest], 1), tr)
        terms.keypoint_term(_project(camera, pinhole, cams, kp), torso, cfg.sigma_px).sum().backward()
        for p in params:
            torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
        opt.step()
    with torch.no_grad():
        kp = kp_model(betas, torch.cat([root[:, None], rest], 1), tr)
        rigid = det * _torso_mask(det, with_face=True)
        score = terms.keypoint_term(_project(camera, pinhole, cams, kp), rigid, cfg.sigma_px)
        if depth is not None:
            along = camera.project(kp)[1]  # depth along the viewing axis, as in the later stages
            score = score + cfg.depth_weight * cfg.sigma_px**2 * terms.depth_term(
                along, depth.repeat_interleave(H, 0), det[..., 2], torch.tensor(DEPTH_PAIRS), cfg.depth_sigma,
                cfg.depth_pair_margin)  # fmt: skip
        score = score.reshape(F, H)
        best = torch.arange(F) * H + score.nan_to_num(float("inf")).argmin(1)
        pose[:, 0] = root.detach()[best]
        _keep(best, transl, cam_params, tr, cams)


@dataclasses.dataclass
class PosePrior:
    """The pose's per-frame priors (pose size, knee bend, joint limits, unobserved rotations): (F, J, 3) -> (F,)."""

    cfg: FitConfig
    pose_weights: torch.Tensor
    knees: list[int]
    lo: torch.Tensor
    hi: torch.Tensor
    blind: torch.Tensor | None

    def __call__(self, pose: torch.Tensor) -> torch.Tensor:
        cfg = self.cfg
        total = cfg.pose_weight * terms.pose_prior(pose[:, 1:], self.pose_weights[1:]) * cfg.sigma_px
        total = total + cfg.bend_weight * terms.bend_prior(pose, self.knees, 0, 1.0)
        total = total + cfg.limit_weight * terms.joint_limit_prior(pose, self.lo, self.hi)
        if self.blind is not None:
            total = total + cfg.unobserved_weight * terms.subspace_prior(pose, self.blind)
        return total


def limb_starts(model: BodyModel, angle: float) -> torch.Tensor:
    """(H, J, 3) pose offsets the body-pose stage starts from: rest first, then each combination of limb
    groups swung ``angle`` forward (arms, legs, both for the body models with rules; rest alone at 0)."""
    groups = list(forward_directions(model).values()) if angle > 0 else []
    starts = [torch.zeros(model.num_joints, 3, dtype=torch.float64)]
    for pick in range(1, 2 ** len(groups)):
        starts.append(angle * sum(d for i, d in enumerate(groups) if pick >> i & 1))
    return torch.stack(starts)


def choose_start(hidden: torch.Tensor, cost: torch.Tensor) -> torch.Tensor:
    """(F,) the start each frame keeps, from (F, H) counts of seen keypoints its fit hides and (F, H) costs:
    start 0 (rest) where it hides none; else, of the starts that hide fewest, the cheapest (a non-finite
    cost never wins)."""
    fewest = hidden.amin(1, keepdim=True)
    cheapest = torch.where(hidden == fewest, cost.nan_to_num(torch.inf), torch.inf).argmin(1)
    return torch.where(hidden[:, 0] == 0, torch.zeros_like(cheapest), cheapest)


def _limbs_by_visibility(points: PosedPoints, seen_by: tuple, pinhole: bool, detected: torch.Tensor,
                         ends: torch.Tensor, betas: torch.Tensor, pose: torch.Tensor, transl: torch.Tensor,
                         cam_params: list[torch.Tensor], cfg: FitConfig, prior: PosePrior,
                         starts: torch.Tensor) -> None:  # fmt: skip
    """The body-pose stage, in place, from each of ``starts`` (H, J, 3; rest first) a frame at once (F x H
    problems in one batch: the stage ties no frames together; a rest start's steps are the plain stage's).
    A frame keeps the pose from rest unless it hides seen limb keypoints (``ends`` (K,) bool) behind the body
    (``seen_by``: posed points with the coarse mesh's vertices, its faces, the camera) and another start hides
    fewer; among those with the fewest, the one whose keypoints and priors cost least.
    A limb swung toward the camera or away from it fits the keypoints alike: their costs differ by the local
    minima reached, not by the side, so cost alone does not choose."""
    F, H = pose.shape[0], len(starts)
    P = (pose.repeat_interleave(H, 0) + starts.repeat(F, 1, 1)).requires_grad_()
    tr, cams = _copies(transl, H), [_copies(c, H) for c in cam_params]
    det = detected.repeat_interleave(H, 0)
    mesh_points, faces, camera = seen_by
    scale = distance_scale(camera, points(betas, pose, transl)[0]) if pinhole else 1.0
    params = [tr] * pinhole + cams + [P]
    opt = Adam(params, lr=cfg.lr * scale)

    def cost() -> torch.Tensor:
        kp2d = _project(camera, pinhole, cams, points(betas, P, tr)[0])
        return terms.keypoint_term(kp2d, det, cfg.sigma_px) + prior(P)

    for _ in range(cfg.iterations[1]):
        opt.zero_grad()
        cost().sum().backward()
        for p in params:
            torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
        opt.step()
    with torch.no_grad():
        kp3d, verts = mesh_points(betas, P, tr)
        hidden = hidden_seen(verts, faces, kp3d, (det[..., 2] >= SEEN) & ends, camera).reshape(F, H)
        best = torch.arange(F) * H + choose_start(hidden, cost().reshape(F, H))
        pose.copy_(P.detach()[best])
        _keep(best, transl, cam_params, tr, cams)


def _result(points, betas, pose, transl, camera, cam_params, detected, few, empty) -> FitResult:
    """Interpolate flagged frames from their neighbours and measure the reprojection residuals."""
    flagged = few | empty
    with torch.no_grad():
        pose_f = interpolate(pose.detach(), flagged)
        if isinstance(camera, PinholeCamera):
            transl_f, cam_f = interpolate(transl.detach(), flagged), camera
        else:
            transl_f = transl.detach()
            cam_f = OrthographicCamera(interpolate(cam_params[0].detach(), flagged).exp(),
                                       interpolate(cam_params[1].detach(), flagged), camera.width, camera.height)  # fmt: skip
        kp2d = cam_f.project(points(betas.detach(), pose_f, transl_f)[0])[0]
        conf = detected[..., 2] > 0
        err = (kp2d - detected[..., :2]).norm(dim=-1)
        residual = torch.where(flagged, torch.nan, (err * conf).sum(-1) / conf.sum(-1).clamp_min(1))
    return FitResult(betas.detach(), pose_f, transl_f, cam_f, flagged, few, empty, residual)


def _torso_mask(detected: torch.Tensor, with_face: bool = False) -> torch.Tensor:
    mask = torch.zeros_like(detected)
    mask[:, list(TORSO) + list(FACE) * with_face] = 1.0
    return mask
