"""One in-memory format for every body model (SMPL-X, Anny, upsampled variants).

Shape vocabulary: V vertices, F faces, J joints, S shape coefficients,
E expression coefficients, P = 9 (J - 1) pose-corrective features.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from delta import DeltaError
from delta.io import save_npz

#: Region labels shared by every body model; the offset loss weights index them.
REGION_NAMES: tuple[str, ...] = ("body", "face", "hands", "feet", "eyes", "mouth")
REGION = {name: i for i, name in enumerate(REGION_NAMES)}

_OPTIONAL = ("posedirs", "exprdirs", "joints_exprdirs", "embed_vertex_ids", "embed_bary", "expression_names")


@dataclasses.dataclass
class BodyModel:
    """A linear body model posed by linear blend skinning (SMPL-X conventions).

    Zero pose is the template's pose; pose parameters rotate each joint in
    world-aligned axes about its rest position (axis-angle by default).
    """

    name: str
    """Which model this is ("anny", "smplx", with a suffix when upsampled)."""
    v_template: torch.Tensor
    """(V, 3) rest vertices at mean shape."""
    faces: torch.Tensor
    """(F, 3) int64 triangle indices."""
    shapedirs: torch.Tensor
    """(V, 3, S) identity blend shapes (scaled so that β ~ N(0, I) where known)."""
    joints_template: torch.Tensor
    """(J, 3) rest joint positions at mean shape."""
    joints_shapedirs: torch.Tensor
    """(J, 3, S) joint blend shapes: J(β) = joints_template + joints_shapedirs β."""
    parents: torch.Tensor
    """(J,) int64 parent index per joint, -1 for the root; parents[j] < j."""
    joint_names: list[str]
    """(J,) names of the joints."""
    weights: torch.Tensor
    """(V, J) skinning weights, rows sum to 1."""
    regions: torch.Tensor
    """(V,) int64 region label per vertex, indices into REGION_NAMES."""
    canonical_pose: torch.Tensor
    """(J, 3) axis-angle pose of the canonical space (NeRF lives there)."""
    posedirs: Optional[torch.Tensor] = None
    """(V, 3, P) pose-corrective blend shapes over (R_j - I), j >= 1, or None."""
    exprdirs: Optional[torch.Tensor] = None
    """(V, 3, E) expression blend shapes, or None."""
    joints_exprdirs: Optional[torch.Tensor] = None
    """(J, 3, E) effect of expressions on joints, or None."""
    embed_vertex_ids: Optional[torch.Tensor] = None
    """(V, 3) int64 base-mesh vertices each vertex interpolates (upsampled models)."""
    embed_bary: Optional[torch.Tensor] = None
    """(V, 3) barycentric weights of those base-mesh vertices."""
    expression_names: list[str] = dataclasses.field(default_factory=list)
    """(E,) names of the expression coefficients (Anny's facial actions), or empty when unnamed."""

    # ------------------------------------------------------------------ sizes
    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_joints(self) -> int:
        return int(self.parents.shape[0])

    @property
    def num_shape(self) -> int:
        return int(self.shapedirs.shape[-1])

    @property
    def num_expression(self) -> int:
        return 0 if self.exprdirs is None else int(self.exprdirs.shape[-1])

    def subtree(self, name: str) -> torch.Tensor:
        """(J,) bool: the joint ``name`` and every joint it carries (none where the model has no such joint)."""
        out = torch.zeros(self.num_joints, dtype=torch.bool)
        if name not in self.joint_names:
            return out
        out[self.joint_names.index(name)] = True
        for j, parent in enumerate(self.parents.tolist()):
            if parent >= 0 and out[parent]:  # parents come first
                out[j] = True
        return out

    # ------------------------------------------------------------ conversion
    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "BodyModel":
        """A copy with floating tensors moved to ``device`` / cast to ``dtype``."""
        changes = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, torch.Tensor):
                cast = dtype if value.is_floating_point() else None
                changes[f.name] = value.to(device=device, dtype=cast)
        return dataclasses.replace(self, **changes)

    def validate(self, source: str = "<memory>") -> "BodyModel":
        """Check shapes and invariants; raise DeltaError naming ``source`` and the key."""
        V, J, S = self.num_vertices, self.num_joints, self.num_shape
        expect = {
            "v_template": (V, 3),
            "faces": (None, 3),
            "shapedirs": (V, 3, S),
            "joints_template": (J, 3),
            "joints_shapedirs": (J, 3, S),
            "weights": (V, J),
            "regions": (V,),
            "canonical_pose": (J, 3),
            "posedirs": (V, 3, 9 * (J - 1)),
            "exprdirs": (V, 3, None),
            "joints_exprdirs": (J, 3, self.num_expression),
            "embed_vertex_ids": (V, 3),
            "embed_bary": (V, 3),
        }
        for key, shape in expect.items():
            value = getattr(self, key)
            if value is None:
                continue
            if value.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, value.shape)):
                raise DeltaError(f"{source}: '{key}' has shape {tuple(value.shape)}, expected {shape} (None = any)")
            if value.is_floating_point() and not torch.isfinite(value).all():
                raise DeltaError(f"{source}: '{key}' contains NaN or infinite values")
        if self.expression_names and len(self.expression_names) != self.num_expression:
            raise DeltaError(f"{source}: 'expression_names' has {len(self.expression_names)} names for "
                             f"{self.num_expression} expression blend shapes")  # fmt: skip
        if len(self.joint_names) != J:
            raise DeltaError(f"{source}: 'joint_names' has {len(self.joint_names)} names for {J} joints")
        parents = self.parents.tolist()
        if parents[0] != -1 or any(not (0 <= p < j) for j, p in enumerate(parents[1:], start=1)):
            raise DeltaError(f"{source}: 'parents' must start with -1 and satisfy 0 <= parents[j] < j")
        if self.faces.numel() and (int(self.faces.min()) < 0 or int(self.faces.max()) >= V):
            raise DeltaError(f"{source}: 'faces' index outside [0, {V})")
        row_sums = self.weights.sum(-1)
        if not torch.allclose(row_sums, torch.ones_like(row_sums), atol=1e-3):
            raise DeltaError(f"{source}: 'weights' rows must sum to 1 (worst {row_sums.sub(1).abs().max():.3g})")
        if self.regions.numel() and (int(self.regions.min()) < 0 or int(self.regions.max()) >= len(REGION_NAMES)):
            raise DeltaError(f"{source}: 'regions' labels must lie in [0, {len(REGION_NAMES)})")
        return self

    # ------------------------------------------------------------------- I/O
    def save(self, path: str | os.PathLike, **metadata: np.ndarray) -> None:
        """Write the model as a pickle-free npz (atomically); ``metadata`` is stored with a ``meta_`` prefix."""
        arrays: dict[str, np.ndarray] = {"name": np.array(self.name), "joint_names": np.array(self.joint_names)}
        if self.expression_names:
            arrays["expression_names"] = np.array(self.expression_names)
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, torch.Tensor):
                arrays[f.name] = value.detach().cpu().numpy()
        arrays.update({f"meta_{k}": np.asarray(v) for k, v in metadata.items()})
        save_npz(path, **arrays)


def load_body_model(path: str | os.PathLike, dtype: torch.dtype = torch.float32) -> BodyModel:
    """Load a model written by :meth:`BodyModel.save`; errors name the file and key."""
    path = Path(path)
    if not path.is_file():
        raise DeltaError(f"body model file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except Exception as exc:  # zipfile / ValueError / OSError: a corrupt or foreign file
        raise DeltaError(f"{path}: not a readable body-model npz ({exc.__class__.__name__}: {exc})") from exc
    fields = {f.name for f in dataclasses.fields(BodyModel)}
    missing = sorted(fields - set(arrays) - set(_OPTIONAL))
    if missing:
        raise DeltaError(
            f"{path}: missing keys {missing}; was it written by 'delta convert-anny' or 'delta load-smplx'?"
        )
    kwargs = {}
    for key in fields & set(arrays):
        value = arrays[key]
        if key == "name":
            kwargs[key] = str(value)
        elif key in ("joint_names", "expression_names"):
            kwargs[key] = [str(n) for n in value]
        elif np.issubdtype(value.dtype, np.integer):
            kwargs[key] = torch.from_numpy(value.astype(np.int64))
        else:
            kwargs[key] = torch.from_numpy(value).to(dtype)
    return BodyModel(**kwargs).validate(str(path))


def load_metadata(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The ``meta_*`` arrays stored beside a body model."""
    with np.load(path, allow_pickle=False) as data:
        return {k[5:]: data[k] for k in data.files if k.startswith("meta_")}
