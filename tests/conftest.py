"""Shared fixtures: small analytic body models, the SMPL-X fixture generator, Anny.

The suite runs in two pytest-xdist workers (``-n 2``, the README's test command): the caches
under ``resources/`` (Anny's build, the converted MediaPipe models, the perceptual weights) are
built once, in the background when a fresh clone runs the whole suite (tests/caches.py), each
worker's torch uses one thread (two workers on two cores), and the end-to-end workflow run, the
longest test, starts first.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from delta.body.model import BodyModel
from delta.host_memory import hold_freed_memory
from tests import caches
from tests.caches import ANNY_CACHE, MODELS_DIR, REPO, exclusive  # noqa: F401 (tests import them from here)

hold_freed_memory()  # the tests' training steps take their memory as a delta command's do

if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)
    if os.environ.get("DELTA_TEST_CACHES_BUILDING"):
        # the background builds come first: the end-to-end run waits for them, and cache-free tests
        # competing with them as equals slowed Anny's build from 1.7 to 4 min (the whole suite 14 -> 16.5 min)
        os.nice(10)

_BACKGROUND: list[subprocess.Popen] = []


def pytest_configure(config):
    """On a whole-suite run in a clone without the caches, start their builds in the background (each under
    its lock, see tests/caches.py): the workers run tests that need none of them meanwhile."""
    if hasattr(config, "workerinput") or config.args_source != pytest.Config.ArgsSource.TESTPATHS:
        return
    log = REPO / "resources" / "caches.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    building = caches.missing()
    if building:
        os.environ["DELTA_TEST_CACHES_BUILDING"] = ",".join(building)  # the workers, started next, yield to them
    for name in building:
        with open(log, "a") as fh:
            _BACKGROUND.append(subprocess.Popen([sys.executable, "-m", "tests.caches", name], cwd=REPO, stdout=fh,
                                                stderr=subprocess.STDOUT))  # fmt: skip


def pytest_unconfigure(config):
    for proc in _BACKGROUND:
        proc.wait()


#: the fixtures that wait for a cache of tests/caches.py (directly or through the fixtures they use)
CACHE_FIXTURES = frozenset({"anny_model", "anny_face_model", "mediapipe_pose_model", "perceptual_weights"})


def pytest_collection_modifyitems(config, items):
    """The end-to-end workflow run first (started last, it would run alone at the end), then the tests that
    need no cache, then those that do: pytest-xdist's work stealing gives each worker a contiguous half of
    this order to start with, so in a fresh clone the second worker runs cache-free tests while the caches
    build, instead of waiting on their locks."""
    items.sort(key=lambda item: (item.name != "test_tiny_configuration_end_to_end",
                                 bool(CACHE_FIXTURES & set(getattr(item, "fixturenames", ())))))  # fmt: skip


def tree_model(dtype=torch.float64, num_shape: int = 2, seed: int = 0) -> BodyModel:
    """A 4-joint tree (root -> a -> b, root -> c); each vertex is bound rigidly to one joint.

    Joints sit at (0,0,0), (1,0,0), (2,0,0), (0,1,0); vertices cluster around them.
    Shape directions and a pose corrective are random but small.
    """
    gen = torch.Generator().manual_seed(seed)
    joints = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], dtype=dtype)
    owner = torch.arange(4).repeat_interleave(5)
    verts = joints[owner] + 0.2 * torch.randn(20, 3, generator=gen, dtype=dtype)
    weights = torch.nn.functional.one_hot(owner, 4).to(dtype)
    return BodyModel(
        name="tree",
        v_template=verts,
        faces=torch.tensor([[0, 1, 2], [5, 6, 7], [10, 11, 12], [15, 16, 17]]),
        shapedirs=0.05 * torch.randn(20, 3, num_shape, generator=gen, dtype=dtype),
        joints_template=joints,
        joints_shapedirs=0.05 * torch.randn(4, 3, num_shape, generator=gen, dtype=dtype),
        parents=torch.tensor([-1, 0, 1, 0]),
        joint_names=["root", "a", "b", "c"],
        weights=weights,
        regions=torch.zeros(20, dtype=torch.int64),
        canonical_pose=torch.zeros(4, 3, dtype=dtype),
        posedirs=0.01 * torch.randn(20, 3, 27, generator=gen, dtype=dtype),
    ).validate("tree fixture")


def soft_tree_model(dtype=torch.float64) -> BodyModel:
    """The tree fixture with blended (non one-hot) skinning weights."""
    m = tree_model(dtype)
    gen = torch.Generator().manual_seed(1)
    w = m.weights + 0.3 * torch.rand(m.weights.shape, generator=gen, dtype=dtype)
    m.weights = w / w.sum(-1, keepdim=True)
    return m


@pytest.fixture
def tree() -> BodyModel:
    return tree_model()


SMPLX_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15]
SMPLX_PARENTS += [20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38]
SMPLX_PARENTS += [21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53]


def make_smplx_arrays(num_vertices: int = 10475, num_components: int = 400, seed: int = 0) -> dict:
    """Random arrays with the official SMPL-X key names, dtypes and shapes (no licensed data)."""
    rng = np.random.default_rng(seed)
    V, J = num_vertices, 55
    v = rng.normal(size=(V, 3)) * np.array([0.3, 0.8, 0.15])
    faces = rng.integers(0, V, size=(2 * V, 3)).astype(np.uint32)
    J_reg = np.zeros((J, V))
    for j in range(J):  # each joint regresses from a few vertices
        idx = rng.choice(V, size=6, replace=False)
        J_reg[j, idx] = 1.0 / 6
    w = rng.random((V, J)) ** 8
    return {
        "v_template": v.astype(np.float64),
        "f": faces,
        "shapedirs": (rng.normal(size=(V, 3, num_components)) * 1e-3),
        "posedirs": (rng.normal(size=(V, 3, 9 * (J - 1))) * 1e-4),
        "J_regressor": J_reg,
        "kintree_table": np.stack([np.array([2**32 - 1] + SMPLX_PARENTS[1:], dtype=np.int64), np.arange(J)]),
        "weights": w / w.sum(1, keepdims=True),
        "hands_componentsl": rng.normal(size=(45, 45)),
        "hands_componentsr": rng.normal(size=(45, 45)),
    }


@pytest.fixture(scope="session")
def anny_model():
    """Anny itself (float64, dense LBS), with its build cache under resources/ (slow the first time)."""
    return caches.anny()


@pytest.fixture(scope="session")
def anny_face_model():
    """Anny with its 52 facial actions (its own build cache entry)."""
    return caches.anny(facial_actions=True)


@pytest.fixture(scope="session")
def anny_conversion(anny_model):
    from delta.body.anny_convert import convert_anny

    return convert_anny(num_shape=32, num_samples=256, seed=0, anny_model=anny_model)


@pytest.fixture(scope="session")
def anny_files(tmp_path_factory, anny_model):
    """A small converted Anny model and its shape space, as the workflow writes them, without the workflow's
    upsampling (``body_model.upsample_level``: 55k vertices where this has 14k): a training step and a
    whole-frame render of the tiny captures cost half as much. The end-to-end run trains on the upsampled
    body; tests of what upsampling changes upsample this one (``upsampled``)."""
    from delta.body.anny_convert import convert_anny

    out = tmp_path_factory.mktemp("anny")
    conv = convert_anny(num_shape=8, num_samples=64, seed=0, merge_bones=["fingers", "toes"], anny_model=anny_model)
    conv.model.to(dtype=torch.float32).save(out / "anny.npz")
    conv.space.save(out / "anny_pca.npz")
    return {"body": str(out / "anny.npz"), "shape_space": str(out / "anny_pca.npz"), "cache": str(ANNY_CACHE)}


def upsampled(path: str, dtype=torch.float32) -> BodyModel:
    """The body model at ``path`` upsampled once, as the workflow's default ``body_model.upsample_level``."""
    from delta.body.model import load_body_model
    from delta.body.upsample import upsample_body_model

    return upsample_body_model(load_body_model(path, dtype=torch.float64), 1).to(dtype=dtype)


@pytest.fixture(scope="session")
def anny_expressions_file(tmp_path_factory, anny_face_model):
    """Anny's facial actions as the expression-space file the workflow writes."""
    from delta.body.expressions import anny_expression_space

    path = tmp_path_factory.mktemp("expressions") / "anny_expressions.npz"
    anny_expression_space(anny_face_model).save(path)
    return str(path)


TINY_SUBJECTS = {
    "tight": dict(seed=1, phenotype={"gender": 0.85}, garments=["tshirt", "trousers"], hair="short", camera="pinhole",
                  distortion=[-0.04, 0.01, 0.0, 0.0, 0.0], resolution=128, turn_frames=5, novel_frames=2,
                  test_view_every=2),
    "loose": dict(seed=2, garments=[{"kind": "dress", "pattern": "dots"}], hair="long", camera="orthographic",
                  resolution=128, turn_frames=4, novel_frames=1, test_view_every=2),
}  # fmt: skip


@pytest.fixture(scope="session")
def tiny_captures(tmp_path_factory, anny_files):
    """The two tiny synthetic subjects, generated once per session."""
    from delta.synthetic.generate import generate, write_peoplesnapshot
    from delta.synthetic.spec import parse_subject

    root = tmp_path_factory.mktemp("synthetic")
    for name, raw in TINY_SUBJECTS.items():
        spec = parse_subject(name, raw)
        generate(spec, anny_files["body"], root / name, anny_files["shape_space"], anny_files["cache"])
        if spec.camera == "pinhole":
            write_peoplesnapshot(root / name, name, root / "ps" / name)
    return root


@pytest.fixture(scope="session")
def mediapipe_pose_model():
    """MediaPipe's pose landmark model in ONNX, converted once (the first run installs the converter)."""
    return caches.mediapipe()


@pytest.fixture(scope="session")
def perceptual_weights():
    """The folder of the shift-tolerant VGG16/AlexNet weights, fetched once from the registry when missing."""
    return caches.stlpips()


# ----------------------------------------------------------- tiny training
def init_from_gt(capture, record_path, out_path):
    """The ground-truth body parameters of the record's frames, written as an init fit would."""
    from delta.data.record import FrameRecord
    from delta.io import save_npz

    gt = np.load(capture / "gt" / "params.npz")
    with FrameRecord(record_path) as rec:
        ids = rec.h5["frame_ids"][:]
        cam = {"camera_model": np.array(rec.h5.attrs["camera_model"])}
        if rec.h5.attrs["camera_model"] == "orthographic":
            cam.update(ortho_scale=rec.h5["ortho_scale"][:], ortho_trans=rec.h5["ortho_trans"][:])
    save_npz(out_path, betas=gt["betas"], poses=gt["poses"][ids], transl=gt["transl"][ids], frame_ids=ids, **cam)


@pytest.fixture(scope="session")
def tiny_training(tmp_path_factory, tiny_captures, anny_files):
    """{subject: {"record", "init", "body"}} for the tiny pinhole (tight) and orthographic (loose) subjects."""
    from delta.data.sources import synthetic_source
    from delta.preprocess.frames import prepare

    root = tmp_path_factory.mktemp("training")
    out = {}
    for name in ("tight", "loose"):
        record = root / name / "frames.h5"
        prepare(synthetic_source(tiny_captures / name, name), record, size=64)
        init_from_gt(tiny_captures / name, record, root / name / "init.npz")
        out[name] = {"record": str(record), "init": str(root / name / "init.npz"), "body": anny_files["body"],
                     "capture": str(tiny_captures / name)}  # fmt: skip
    return out


#: a few stage-1 steps at 32²: enough for the code paths of evaluation and export, not for quality
TINY_STAGE1 = {"resolution": 32, "render": {"samples": 8},
               "stage1": {"iterations": 6, "rays": 128, "checkpoint_every": 6, "preview_every": 0}}  # fmt: skip


@pytest.fixture(scope="session")
def tiny_trained(tmp_path_factory, tiny_training):
    """{subject: {..., "model"}}: a stage-1 model.pt trained for a few steps from the GT init."""
    from delta.training.run import run_stage

    root = tmp_path_factory.mktemp("trained")
    out = {}
    for name, inputs in tiny_training.items():
        run_stage(1, inputs["record"], inputs["body"], inputs["init"], str(root / name), "fast", [TINY_STAGE1])
        out[name] = dict(inputs, model=str(root / name / "model.pt"))
    return out
