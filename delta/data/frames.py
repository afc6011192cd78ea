"""Frame data: a frame record resized to the preset's resolution, and ray sampling (read by training,
evaluation and export alike).

Targets follow the evaluation convention of the anchors: the image composited on the
background colour with the person alpha (white by default).
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import torch

from delta import DeltaError
from delta.body.face_points import FacePoints
from delta.cameras.models import OrthographicCamera, PinholeCamera
from delta.data.record import FrameRecord
from delta.metrics import outline_band


#: Bytes a training pixel holds (colour, person, exterior, interior, and hair where layers are split).
BYTES_PER_PIXEL = 8


class ByteFrames:
    """Per-pixel values in [0, 1] held as bytes (round(255 v)) and read as floats: a quarter of the
    memory of float frames, so that a capture's frames fit at its own resolution (400 frames of 512²
    with their masks: 0.7 GB instead of 2.9). Indexing returns float32; a whole read is ``[:]``."""

    def __init__(self, values: torch.Tensor):
        if values.dtype != torch.uint8:
            raise TypeError(f"ByteFrames holds uint8 values, got {values.dtype}")
        self.bytes = values

    @staticmethod
    def quantise(values: np.ndarray) -> np.ndarray:
        """float values in [0, 1] as the bytes that hold them."""
        return np.rint(np.clip(values, 0.0, 1.0) * 255.0).astype(np.uint8)

    def __getitem__(self, index) -> torch.Tensor:
        return self.bytes[index].float() / 255.0

    @property
    def shape(self) -> torch.Size:
        return self.bytes.shape

    def total(self, index) -> float:
        """The sum of the values selected by ``index``, without reading them as floats."""
        return float(self.bytes[index].sum(dtype=torch.float64)) / 255.0


@dataclasses.dataclass
class FrameData:
    """All frames of a subject at the training resolution (N frames, H = W = n), held as bytes: index
    a field to read it as floats (``data.images[f]``)."""

    images: ByteFrames
    """(N, n, n, 3) targets in [0, 1], composited on the background."""
    person: ByteFrames
    """(N, n, n) person alpha in [0, 1]."""
    exterior: ByteFrames
    """(N, n, n) clothing or hair in [0, 1]."""
    interior: ByteFrames
    """(N, n, n) visible body (person minus exterior)."""
    boxes: torch.Tensor
    """(N, 4) int64 pixel box (i0, i1, j0, j1) around the person plus a margin."""
    train: np.ndarray
    """Indices of the training frames."""
    split: np.ndarray
    """(N,) split of each frame (0 train, 1 test view, 2 test pose)."""
    frame_ids: np.ndarray
    camera: object
    """The record's camera rescaled to n (pinhole) or the record's per-frame orthographic camera."""
    skin_color: torch.Tensor
    """(3,) average colour of the visible body over the training frames."""
    hair: ByteFrames | None = None
    """(N, n, n) hair in [0, 1] (part of ``exterior``), loaded for an exterior of separate layers."""
    face: FacePoints | None = None
    """Where the record's face points lie on the body mesh (None: it tracks no face)."""
    face_points: torch.Tensor | None = None
    """(N, K, 3) the detected face points (u, v in this resolution's pixels, confidence), with ``face``."""

    @property
    def resolution(self) -> int:
        return int(self.images.shape[1])


#: how far (the record's pixels) a part claims the person's unlabelled pixels around it
FRINGE_REACH = 3.0


def claim_fringe(alpha: np.ndarray, parts: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The (H, W) bool part masks with the person's unlabelled fringe given to the nearest part.

    A part label says what a pixel's centre sees, while the person's alpha (H, W, 0-255) also covers the
    pixels of its outline whose centre missed the person (an edge pixel a third covered) and a matting
    model's soft fringe. Left unclaimed, no part of the avatar is asked to cover them: the exterior's target
    is zero there and the body lies further in, so the avatar's outline settled a third of a pixel inside
    the person's all round, and that band held 70 % of a held-out frame's squared error (tight at 512²:
    docs/method.md). Each pixel of the person that no part labels and that lies within ``FRINGE_REACH``
    pixels of where the person is not (the fringe: not a patch of skin a parser left unlabelled inside the
    person) goes to the part of the nearest labelled pixel within that reach."""
    owner = np.full(alpha.shape, -1, np.int8)  # each labelled pixel's part (the first named where they overlap)
    for k, m in reversed(list(enumerate(parts.values()))):
        owner[m] = k
    labelled = owner >= 0
    person = alpha > 0
    free = person & ~labelled
    if free.any():  # distance of each person pixel to the nearest pixel without the person
        free &= cv2.distanceTransform(person.astype(np.uint8), cv2.DIST_L2, 5) <= FRINGE_REACH
    if not free.any() or not labelled.any():
        return parts
    # one transform: each pixel's distance to the nearest labelled pixel, and which pixel that is
    dist, nearest = cv2.distanceTransformWithLabels((~labelled).astype(np.uint8), cv2.DIST_L2, 5,
                                                    labelType=cv2.DIST_LABEL_PIXEL)  # fmt: skip
    ys, xs = np.nonzero(labelled)  # label k (1-based) is the k-th labelled pixel in row-major order
    claim = free & (dist <= FRINGE_REACH)
    by = owner[ys[nearest - 1], xs[nearest - 1]]
    return {name: m | (claim & (by == k)) for k, (name, m) in enumerate(parts.items())}


def _resize(a: np.ndarray, n: int) -> np.ndarray:
    return a if a.shape[0] == n else cv2.resize(a, (n, n), interpolation=cv2.INTER_AREA)


def _box(mask: np.ndarray, margin: float) -> tuple[int, int, int, int]:
    n = mask.shape[0]
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if len(rows) == 0:
        return 0, n, 0, n
    pad = int(np.ceil(margin * max(rows[-1] - rows[0], cols[-1] - cols[0], 1)))
    return max(rows[0] - pad, 0), min(rows[-1] + 1 + pad, n), max(cols[0] - pad, 0), min(cols[-1] + 1 + pad, n)


def rescale_camera(camera, source: int, n: int):
    """A record camera of a source×source image, for an n×n image of the same crop."""
    if isinstance(camera, PinholeCamera):
        K = camera.K.clone()
        K[:2] *= n / source
        return PinholeCamera(K, camera.R, camera.t, camera.dist, n, n)
    return OrthographicCamera(camera.scale, camera.trans, n, n)


def load_frames(record_path, resolution: int, background=(1.0, 1.0, 1.0), box_margin: float = 0.1,
                hair: bool = False) -> FrameData:  # fmt: skip
    """Read and resize a frame record, frame by frame into bytes (N × resolution² × 7 bytes stay in
    memory; ``hair``: the hair mask too, zeros where the record has none)."""
    bg = np.asarray(background, dtype=np.float32)
    with FrameRecord(record_path) as rec:
        n_frames, src = len(rec), rec.size
        has = [m for m in ("clothing", "hair") if m in rec.h5]
        if not has:
            raise DeltaError(f"{record_path}: no 'clothing' or 'hair' mask; the parse step must run first")
        split, frame_ids = rec.h5["split"][:], rec.h5["frame_ids"][:]
        train = np.flatnonzero(split == 0)
        if len(train) == 0:
            raise DeltaError(f"{record_path}: no training frames (split 0)")
        shape = (n_frames, resolution, resolution)
        fields = {k: np.empty(shape + ((3,) if k == "images" else ()), np.uint8)
                  for k in ("images", "person", "exterior", "interior") + (("hair",) if hair else ())}  # fmt: skip
        boxes, skin_sum, skin_weight = [], np.zeros(3), 0.0
        labels = has + (["skin"] if "skin" in rec.h5 else [])
        for i in range(n_frames):
            alpha = rec.h5["person"][i]
            parts = claim_fringe(alpha, {m: rec.h5[m][i] > 0 for m in labels})
            a = _resize(alpha.astype(np.float32) / 255.0, resolution)
            img = _resize(rec.h5["images"][i].astype(np.float32) / 255.0, resolution)
            img = img * a[..., None] + bg * (1 - a[..., None])
            e = np.minimum(_resize(np.any([parts[m] for m in has], 0).astype(np.float32), resolution), a)
            inside = np.clip(a - e, 0.0, 1.0)
            for key, v in (("images", img), ("person", a), ("exterior", e), ("interior", inside)):
                fields[key][i] = ByteFrames.quantise(v)
            if hair:
                h = _resize(parts["hair"].astype(np.float32), resolution) if "hair" in has else np.zeros_like(a)
                fields["hair"][i] = ByteFrames.quantise(np.minimum(h, a))
            if split[i] == 0:
                w = fields["interior"][i].astype(np.float64) / 255.0
                skin_sum += (fields["images"][i].astype(np.float64) / 255.0 * w[..., None]).reshape(-1, 3).sum(0)
                skin_weight += w.sum()
            boxes.append(_box(fields["person"][i] > 127, box_margin))
        camera = rescale_camera(rec.camera(), src, resolution)
        face = rec.face_embedding()
        seen = None
        if face is not None:  # pixel coordinates (a pixel's centre at +0.5) scale with the image
            seen = torch.from_numpy(rec.h5["face_points"][:].astype(np.float32))
            seen[..., :2] *= resolution / src
    held = {k: ByteFrames(torch.from_numpy(v)) for k, v in fields.items()}
    skin = torch.from_numpy(skin_sum / max(skin_weight, 1e-6)).float()
    return FrameData(held["images"], held["person"], held["exterior"], held["interior"],
                     torch.tensor(boxes, dtype=torch.int64), train, split, frame_ids, camera, skin, held.get("hair"),
                     face, seen)  # fmt: skip


@dataclasses.dataclass
class FullFrames:
    """Some frames of a record whole, at the capture's scoring size (H×W), for scoring and exports."""

    rows: list[int]
    """The record's frame indices, in the order of the arrays."""
    images: torch.Tensor
    """(F, H, W, 3) in [0, 1], composited on the background."""
    person: torch.Tensor
    """(F, H, W) person alpha."""
    parts: dict[str, torch.Tensor]
    """'clothing' / 'hair': (F, H, W) bool, the masks the record holds."""
    exterior: torch.Tensor
    """(F, H, W) clothing or hair, inside the person."""
    interior: torch.Tensor
    """(F, H, W) visible body."""
    crop: tuple[int, int, int]
    """(u0, v0, side) of the record's crop, in the capture's pixels."""
    source_size: tuple[int, int]
    """(W, H) of the capture."""

    @property
    def size(self) -> tuple[int, int]:
        """(W, H)."""
        return int(self.images.shape[2]), int(self.images.shape[1])

    def view_geometry(self, n: int) -> tuple[tuple[float, float], tuple[float, float]]:
        """(scale, shift) taking these frames' pixel coordinates to those of the crop at n×n:
        capture pixel = full pixel × capture/full size, crop pixel = (capture pixel − corner) × n/side."""
        (W, H), (Ws, Hs) = self.source_size, self.size
        u0, v0, side = self.crop
        k = n / side
        return (W / Ws * k, H / Hs * k), (-u0 * k, -v0 * k)


def load_full_frames(record_path, rows: list[int], background=(1.0, 1.0, 1.0)) -> FullFrames:
    """The record's whole frames ``rows`` (its ``full`` group), composited on the background."""
    bg = np.asarray(background, dtype=np.float32)
    with FrameRecord(record_path) as rec:
        if "full" not in rec.h5:
            raise DeltaError(f"{record_path}: no whole frames to score (the 'full' group); the record was "
                             "prepared by an older version: delete it and rerun the prepare_frames rule")  # fmt: skip
        g = rec.h5["full"]
        imgs, person, parts = [], [], {m: [] for m in ("clothing", "hair") if m in g}
        for r in rows:
            a = g["person"][r].astype(np.float32) / 255.0
            imgs.append(g["images"][r].astype(np.float32) / 255.0 * a[..., None] + bg * (1 - a[..., None]))
            person.append(a)
            for m in parts:
                parts[m].append(g[m][r] > 0)
        u0, v0, side, _ = (int(x) for x in rec.h5.attrs["crop"])
        W, H = (int(x) for x in rec.h5.attrs["source_size"])
    person_t = torch.from_numpy(np.stack(person))
    parts_t = {m: torch.from_numpy(np.stack(v)) for m, v in parts.items()}
    ext = torch.zeros_like(person_t)
    for m in parts_t.values():
        ext = torch.maximum(ext, m.float())
    ext = torch.minimum(ext, person_t)
    return FullFrames(list(rows), torch.from_numpy(np.stack(imgs)), person_t, parts_t, ext,
                      (person_t - ext).clamp(0, 1), (u0, v0, side), (W, H))  # fmt: skip


def frame_times(frame_ids: np.ndarray, train: np.ndarray, split: np.ndarray | None = None) -> torch.Tensor:
    """(N,) each frame's time in the training sequence, 0 at its first frame and 1 at its last.

    NaN for frames outside it (a novel-pose sequence): their dynamics are unknown. Held-out
    frames between training frames (a held-out view) get their place in the sequence; with
    ``split`` (0 train, 1 held-out view, 2 novel pose), a held-out view before the first or after
    the last training frame is still of that sequence and gets the time of its nearer end.
    """
    ids = np.asarray(frame_ids, dtype=np.float64)
    lo, hi = ids[train].min(), ids[train].max()
    tau = (ids - lo) / max(hi - lo, 1.0)
    inside = (ids >= lo) & (ids <= hi)
    if split is not None:
        inside |= np.asarray(split) == 1
    return torch.from_numpy(np.where(inside, np.clip(tau, 0.0, 1.0), np.nan)).float()


def _central(a: int, b: int, frac: float) -> tuple[int, int]:
    """The central ``frac`` of the index range [a, b), at least one index."""
    half, mid = (b - a) * frac / 2, (a + b) / 2
    lo = min(max(int(np.floor(mid - half + 0.5)), a), b - 1)
    return lo, min(max(int(np.floor(mid + half + 0.5)), lo + 1), b)


@dataclasses.dataclass
class RayBatch:
    frame: int
    pixels: torch.Tensor
    """(R, 2) pixel centres (u, v)."""
    rgb: torch.Tensor
    """(R, 3) targets."""
    person: torch.Tensor
    exterior: torch.Tensor
    interior: torch.Tensor
    patch: int = 0
    """The first patch² rays form a patch (row-major), 0 when none."""
    hair: torch.Tensor | None = None
    """(R,) the hair mask (part of ``exterior``) where the frames hold it."""


def box_rays(data: FrameData, frame: int, box: tuple[int, int, int, int], most: int) -> RayBatch:
    """The pixel centres of rows ``box`` [i0, i1) and columns [j0, j1) of a frame (clipped to it), every
    pixel or, where that would be more than ``most``, every k-th row and column."""
    n = data.resolution
    i0, i1, j0, j1 = max(box[0], 0), min(box[1], n), max(box[2], 0), min(box[3], n)
    stride = max(1, math.ceil(math.sqrt(max(i1 - i0, 0) * max(j1 - j0, 0) / most)))
    ii, jj = torch.meshgrid(torch.arange(i0, i1, stride), torch.arange(j0, j1, stride), indexing="ij")
    ii, jj = ii.reshape(-1), jj.reshape(-1)
    pixels = torch.stack([jj.float(), ii.float()], dim=-1) + 0.5
    hair = data.hair[frame, ii, jj] if data.hair is not None else None
    return RayBatch(frame, pixels, data.images[frame, ii, jj], data.person[frame, ii, jj],
                    data.exterior[frame, ii, jj], data.interior[frame, ii, jj], 0, hair)  # fmt: skip


EDGE_PX = 2
"""Half-width (pixels) of the person's outline band (:func:`delta.metrics.outline_band`) that
:func:`sample_rays` draws its edge rays from."""


def sample_rays(data: FrameData, frame: int, num: int, generator: torch.Generator, patch: int = 0,
                jitter: bool = True, crop: float = 1.0, edge: float = 0.0) -> RayBatch:  # fmt: skip
    """``num`` random pixels inside the frame's person box (rays elsewhere see only background),
    preceded by one ``patch``×``patch`` block of neighbouring pixels when ``patch`` > 0.

    ``edge`` > 0: that share of the ``num`` pixels is drawn from the person's outline instead
    (:func:`delta.metrics.outline_band`: within :data:`EDGE_PX` pixels of the person mask's edge), where a
    render's error gathers (the silhouette's place is the geometry's, and a pixel off there costs the
    whole contrast against the background).

    ``crop`` < 1 draws them from the box's central part of that fraction of its sides instead
    (NeRF's "precrop": mostly person, so that early steps do not teach an empty field).

    With ``jitter`` each random ray passes through a uniform point of its pixel, not its centre:
    a target pixel is the area average of the scene over the pixel (the frames are downsampled
    photographs), and a ray at a uniform point has that average as its expectation — at the
    person's edge too, where centre rays would teach a fuzzy silhouette. Patch rays stay at the
    centres (a regular image for the semantic loss).
    """
    i0, i1, j0, j1 = data.boxes[frame].tolist()
    if crop < 1.0:
        i0, i1, j0, j1 = (*_central(i0, i1, crop), *_central(j0, j1, crop))
    ii = torch.randint(i0, i1, (num,), generator=generator)
    jj = torch.randint(j0, j1, (num,), generator=generator)
    if patch:
        pi = int(torch.randint(i0, max(i1 - patch, i0) + 1, (1,), generator=generator))
        pj = int(torch.randint(j0, max(j1 - patch, j0) + 1, (1,), generator=generator))
        gi, gj = torch.meshgrid(torch.arange(patch) + pi, torch.arange(patch) + pj, indexing="ij")
        n = data.resolution
        ii = torch.cat([gi.reshape(-1).clamp(max=n - 1), ii])
        jj = torch.cat([gj.reshape(-1).clamp(max=n - 1), jj])
    at_edge = round(edge * num) if crop >= 1.0 else 0
    if at_edge:  # drawn after the box's pixels and the patch, which stay those of a step without them
        band = torch.nonzero(outline_band(data.person[frame] > 0.5, EDGE_PX))
        if len(band):
            pick = band[torch.randint(len(band), (at_edge,), generator=generator)]
            first = patch * patch  # the random pixels follow the patch's
            ii[first : first + at_edge], jj[first : first + at_edge] = pick[:, 0], pick[:, 1]
    offset = torch.full((len(ii), 2), 0.5)
    if jitter:
        offset[patch * patch :] = torch.rand((num, 2), generator=generator)
    pixels = torch.stack([jj.float(), ii.float()], dim=-1) + offset
    hair = data.hair[frame, ii, jj] if data.hair is not None else None
    return RayBatch(frame, pixels, data.images[frame, ii, jj], data.person[frame, ii, jj],
                    data.exterior[frame, ii, jj], data.interior[frame, ii, jj], patch, hair)  # fmt: skip
