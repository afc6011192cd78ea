"""onnxruntime adapters for third-party ONNX exports: person mattes, clothing and face parsing.

Each adapter takes one RGB frame, ``(H, W, 3) uint8``, and returns a per-pixel map
of the same ``(H, W)`` size:

- ``RobustVideoMatting``: the official RVM export (``rvm_mobilenetv3_fp32.onnx``,
  ``rvm_resnet50_fp16.onnx``, ...); recurrent, so frames must come in video order.
- ``MODNet``: the official MODNet ONNX export (``modnet.onnx``); per frame.
- ``ClothSegmentation``: the U²-Net cloth segmentation export used by rembg
  (``u2net_cloth_seg.onnx``); classes background / upper / lower / full-body clothes.
- ``FaceParsing``: BiSeNet exports of face-parsing.PyTorch; the 19 CelebAMask-HQ classes.

``open_session`` checks a file's input names and ranks before anything runs, so
a wrong or corrupt download fails with a ``DeltaError`` that names the file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import cv2
import numpy as np
import onnxruntime as ort

from delta import DeltaError

#: ImageNet normalisation of RGB / 255 (cloth and face parsing).
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

#: Class names of ``u2net_cloth_seg.onnx``, by class id.
CLOTH_CLASSES: tuple[str, ...] = ("background", "upper_clothes", "lower_clothes", "full_body_clothes")

#: Class names of the face-parsing.PyTorch BiSeNet (CelebAMask-HQ labels), by class id.
FACE_PARSING_CLASSES: tuple[str, ...] = (
    "background", "skin", "l_brow", "r_brow", "l_eye", "r_eye", "eye_g", "l_ear", "r_ear", "ear_r",
    "nose", "mouth", "u_lip", "l_lip", "neck", "neck_l", "cloth", "hair", "hat",
)  # fmt: skip

#: Face-parsing ids that are the bare face: skin, brows, eyes, ears, nose, mouth, lips.
#: Eyeglasses (6) and earrings (9) are accessories, neck (14) is not face.
FACE_SKIN_CLASSES: tuple[int, ...] = (1, 2, 3, 4, 5, 7, 8, 10, 11, 12, 13)
HAIR_CLASS = 17

#: Wildcard key of ``expected_inputs``: one more input of that rank, whatever its name.
ANY_NAME = "*"


def _shape_str(shape: Sequence) -> str:
    return "(" + ", ".join("?" if d is None else str(d) for d in shape) + ")"


def open_session(
    path: str | Path,
    expected_inputs: Mapping[str, int],
    expected_outputs: int | None = None,
    threads: int = 1,
    config_key: str | None = None,
) -> ort.InferenceSession:
    """Open an ONNX model on the CPU and check its signature.

    ``expected_inputs`` maps input name -> rank; the model must have exactly these
    inputs. The key ``ANY_NAME`` ("*") stands for one input of that rank with any
    name. ``expected_outputs`` is the least number of outputs the model must have.
    ``config_key`` names the config key that sets ``path``, for the error messages.
    """
    path = Path(path)
    where = f"set {config_key}" if config_key else "set its path"
    if not path.is_file():
        raise DeltaError(f"ONNX model not found: {path}; download it and {where} in the config")
    options = ort.SessionOptions()
    options.intra_op_num_threads = int(threads)
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    try:
        model = ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own pybind exception types
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DeltaError(f"{path}: not a readable ONNX model ({first}); re-download it or {where}") from exc

    found = {i.name: list(i.shape) for i in model.get_inputs()}
    named = {k: r for k, r in expected_inputs.items() if k != ANY_NAME}
    ok = all(name in found and len(found[name]) == rank for name, rank in named.items())
    extra = [n for n in found if n not in named]
    if ANY_NAME in expected_inputs:
        ok = ok and len(extra) == 1 and len(found[extra[0]]) == expected_inputs[ANY_NAME]
    else:
        ok = ok and not extra
    if not ok:
        want = ", ".join(f"{n} (rank {r})" for n, r in expected_inputs.items())
        got = ", ".join(f"{n} {_shape_str(s)}" for n, s in found.items())
        raise DeltaError(f"{path}: unexpected ONNX inputs; expected {want}; found {got}. Is this the right model?")
    outputs = model.get_outputs()
    if expected_outputs is not None and len(outputs) < expected_outputs:
        got = ", ".join(f"{o.name} {_shape_str(o.shape)}" for o in outputs)
        raise DeltaError(f"{path}: expected at least {expected_outputs} ONNX output(s), found {got or 'none'}")
    return model


def check_frame(frame: np.ndarray, model: str | Path) -> np.ndarray:
    """Return ``frame`` if it is an RGB ``(H, W, 3) uint8`` array, else raise naming ``model``."""
    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        got = f"{frame.dtype} {frame.shape}" if isinstance(frame, np.ndarray) else type(frame).__name__
        raise DeltaError(f"{model}: expected an RGB frame as a uint8 array of shape (H, W, 3), got {got}")
    if frame.shape[0] == 0 or frame.shape[1] == 0:
        raise DeltaError(f"{model}: empty frame of shape {frame.shape}")
    return frame


def _resize(image: np.ndarray, width: int, height: int, nearest: bool = False) -> np.ndarray:
    """cv2 resize to ``(height, width, ...)``: area when shrinking, linear when enlarging."""
    if image.shape[1] == width and image.shape[0] == height:
        return image
    if nearest:
        interp = cv2.INTER_NEAREST
    else:
        interp = cv2.INTER_AREA if width * height < image.shape[0] * image.shape[1] else cv2.INTER_LINEAR
    return cv2.resize(image, (width, height), interpolation=interp)


def to_nchw(rgb: np.ndarray, mean: Sequence[float], std: Sequence[float]) -> np.ndarray:
    """``(H, W, 3) uint8`` -> ``(1, 3, H, W) float32`` of ``(rgb / 255 - mean) / std``."""
    x = (rgb.astype(np.float32) / 255.0 - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None])


def _numpy_dtype(onnx_type: str) -> type:
    return np.float16 if onnx_type == "tensor(float16)" else np.float32


class RobustVideoMatting:
    """Robust Video Matting (Lin et al. 2022), official ONNX export; recurrent over frames.

    Signature: ``src (B, 3, H, W)`` RGB in [0, 1], recurrent states ``r1i .. r4i``
    (zeros of shape (1, 1, 1, 1) at the first frame), ``downsample_ratio (1,)`` float32;
    outputs ``fgr (B, 3, H, W)``, ``pha (B, 1, H, W)``, ``r1o .. r4o``. Each call feeds the
    states of the previous call; ``reset()`` starts a new clip, and so does a change of
    frame size. ``downsample_ratio=None`` uses ``min(1, 512 / max(H, W))`` per frame size,
    as the RVM authors recommend. fp16 exports are fed float16 ``src`` and states.
    """

    STATES = ("r1i", "r2i", "r3i", "r4i")

    def __init__(
        self, path: str | Path, downsample_ratio: float | None = None, threads: int = 1, config_key: str | None = None
    ) -> None:
        self.path = Path(path)
        if downsample_ratio is not None and not 0.0 < float(downsample_ratio) <= 1.0:
            raise DeltaError(f"{self.path}: downsample_ratio must lie in (0, 1], got {downsample_ratio}")
        self.downsample_ratio = downsample_ratio
        inputs = {"src": 4, **{s: 4 for s in self.STATES}, "downsample_ratio": 1}
        self.session = open_session(self.path, inputs, 6, threads, config_key)
        names = [o.name for o in self.session.get_outputs()]
        missing = [n for n in ("pha", "r1o", "r2o", "r3o", "r4o") if n not in names]
        if missing:
            raise DeltaError(f"{self.path}: RVM outputs {missing} are missing; found {names}")
        src = next(i for i in self.session.get_inputs() if i.name == "src")
        self._dtype = _numpy_dtype(src.type)
        self._size: tuple[int, int] | None = None
        self.reset()

    def reset(self) -> None:
        """Forget the recurrent states (start of a new clip)."""
        self._states = [np.zeros((1, 1, 1, 1), self._dtype) for _ in self.STATES]
        self._size = None

    @property
    def states(self) -> tuple[np.ndarray, ...]:
        """The recurrent states the next call will feed, ``r1i .. r4i``."""
        return tuple(self._states)

    def ratio(self, height: int, width: int) -> float:
        """The downsample ratio fed for a ``height x width`` frame."""
        if self.downsample_ratio is not None:
            return float(self.downsample_ratio)
        return min(1.0, 512.0 / max(height, width))

    def __call__(self, frame_rgb_uint8: np.ndarray) -> np.ndarray:
        """``(H, W, 3) uint8`` RGB -> ``(H, W) float32`` alpha in [0, 1]."""
        frame = check_frame(frame_rgb_uint8, self.path)
        h, w = frame.shape[:2]
        if self._size != (h, w):
            self.reset()
            self._size = (h, w)
        src = (frame.astype(np.float32) / 255.0).transpose(2, 0, 1)[None].astype(self._dtype)
        feed = {"src": np.ascontiguousarray(src), **dict(zip(self.STATES, self._states))}
        feed["downsample_ratio"] = np.array([self.ratio(h, w)], np.float32)
        pha, *states = self.session.run(["pha", "r1o", "r2o", "r3o", "r4o"], feed)
        if pha.shape != (1, 1, h, w):
            raise DeltaError(f"{self.path}: pha has shape {pha.shape}, expected (1, 1, {h}, {w})")
        self._states = [np.asarray(s, self._dtype) for s in states]
        return np.clip(pha[0, 0].astype(np.float32), 0.0, 1.0)


def modnet_size(height: int, width: int, ref_size: int = 512) -> tuple[int, int]:
    """MODNet's input ``(height, width)``: short side ``ref_size``, both floored to multiples of 32.

    The official demo skips the rescale when ``min(H, W) <= ref_size <= max(H, W)``;
    here the short side is always ``ref_size`` so every frame size sees the same scale.
    """
    scale = ref_size / min(height, width)
    return max(32, int(height * scale) // 32 * 32), max(32, int(width * scale) // 32 * 32)


class MODNet:
    """MODNet (Ke et al. 2022) portrait matting, official ONNX export; per frame.

    Signature: ``input (1, 3, h, w)`` float32 of ``(rgb / 255 - 0.5) / 0.5`` at
    ``modnet_size(H, W, ref_size)``; output ``output (1, 1, h, w)`` matte in [0, 1],
    resized back to ``(H, W)``.
    """

    def __init__(self, path: str | Path, ref_size: int = 512, threads: int = 1, config_key: str | None = None) -> None:
        self.path = Path(path)
        self.ref_size = int(ref_size)
        self.session = open_session(self.path, {"input": 4}, 1, threads, config_key)

    def __call__(self, frame_rgb_uint8: np.ndarray) -> np.ndarray:
        """``(H, W, 3) uint8`` RGB -> ``(H, W) float32`` alpha in [0, 1]."""
        frame = check_frame(frame_rgb_uint8, self.path)
        h, w = frame.shape[:2]
        rh, rw = modnet_size(h, w, self.ref_size)
        x = to_nchw(_resize(frame, rw, rh), (0.5, 0.5, 0.5), (0.5, 0.5, 0.5))
        matte = self.session.run(None, {"input": x})[0]
        if matte.ndim != 4 or matte.shape[:2] != (1, 1):
            raise DeltaError(f"{self.path}: output has shape {matte.shape}, expected (1, 1, h, w)")
        return np.clip(_resize(matte[0, 0].astype(np.float32), w, h), 0.0, 1.0)


class _Parser:
    """A per-pixel classifier: ImageNet-normalised ``(1, 3, size, size)`` in, ``(1, C, size, size)`` logits out."""

    num_classes: int
    default_size: int

    def __init__(
        self,
        path: str | Path,
        size: int | None,
        mean: Sequence[float],
        std: Sequence[float],
        threads: int,
        config_key: str | None,
    ) -> None:
        self.path = Path(path)
        self.session = open_session(self.path, {ANY_NAME: 4}, 1, threads, config_key)
        inp = self.session.get_inputs()[0]
        self.input_name = inp.name
        static = [d for d in inp.shape[2:] if isinstance(d, int)]
        self.size = int(size if size is not None else static[0] if static else self.default_size)
        channels = inp.shape[1]
        if any(d != self.size for d in static) or (isinstance(channels, int) and channels != 3):
            raise DeltaError(
                f"{self.path}: input {inp.name} has shape {_shape_str(inp.shape)}, "
                f"expected (1, 3, {self.size}, {self.size})"
            )
        self.mean, self.std = tuple(mean), tuple(std)

    def __call__(self, frame_rgb_uint8: np.ndarray) -> np.ndarray:
        """``(H, W, 3) uint8`` RGB -> ``(H, W) uint8`` class map (argmax of the logits)."""
        frame = check_frame(frame_rgb_uint8, self.path)
        h, w = frame.shape[:2]
        x = to_nchw(_resize(frame, self.size, self.size), self.mean, self.std)
        logits = self.session.run(None, {self.input_name: x})[0]
        if logits.ndim != 4 or logits.shape[:2] != (1, self.num_classes):
            raise DeltaError(
                f"{self.path}: first output has shape {logits.shape}, expected (1, {self.num_classes}, h, w)"
            )
        labels = np.argmax(logits[0], axis=0).astype(np.uint8)
        return _resize(labels, w, h, nearest=True)


class ClothSegmentation(_Parser):
    """U²-Net cloth segmentation (``u2net_cloth_seg.onnx``, as rembg runs it).

    Input: one rank-4 tensor, ``(1, 3, 768, 768)`` float32, ImageNet-normalised RGB / 255
    (rembg's choice; the training repo, levindabhi/cloth-segmentation, used mean = std = 0.5,
    which ``mean`` / ``std`` can select). First output: ``(1, 4, 768, 768)`` logits over
    ``CLOTH_CLASSES``: 0 background, 1 upper clothes, 2 lower clothes, 3 full-body clothes.
    """

    num_classes = len(CLOTH_CLASSES)
    default_size = 768

    def __init__(
        self,
        path: str | Path,
        size: int | None = None,
        threads: int = 1,
        mean: Sequence[float] = IMAGENET_MEAN,
        std: Sequence[float] = IMAGENET_STD,
        config_key: str | None = None,
    ) -> None:
        super().__init__(path, size, mean, std, threads, config_key)


def clothing_mask(class_map: np.ndarray) -> np.ndarray:
    """``(H, W)`` cloth class map -> ``(H, W) bool``, True on any clothes (classes 1..3)."""
    return (class_map >= 1) & (class_map <= 3)


class FaceParsing(_Parser):
    """BiSeNet face parsing (zllrunning/face-parsing.PyTorch exports).

    Input: one rank-4 tensor, ``(1, 3, 512, 512)`` float32, ImageNet-normalised RGB / 255.
    First output: ``(1, 19, 512, 512)`` logits over ``FACE_PARSING_CLASSES`` (the BiSeNet
    auxiliary outputs ``out16``, ``out32`` are ignored). The network expects a face crop.
    """

    num_classes = len(FACE_PARSING_CLASSES)
    default_size = 512

    def __init__(
        self, path: str | Path, size: int | None = None, threads: int = 1, config_key: str | None = None
    ) -> None:
        super().__init__(path, size, IMAGENET_MEAN, IMAGENET_STD, threads, config_key)


def hair_mask(class_map: np.ndarray) -> np.ndarray:
    """``(H, W)`` face-parsing class map -> ``(H, W) bool``, True on hair (17)."""
    return class_map == HAIR_CLASS


def face_skin_mask(class_map: np.ndarray) -> np.ndarray:
    """``(H, W)`` face-parsing class map -> ``(H, W) bool`` on the bare face, ``FACE_SKIN_CLASSES``.

    Skin, brows, eyes, ears, nose, mouth and lips (1-5, 7, 8, 10-13); eyeglasses (6),
    earrings (9), neck (14, 15), cloth, hair and hat are not face skin.
    """
    return np.isin(class_map, FACE_SKIN_CLASSES)
