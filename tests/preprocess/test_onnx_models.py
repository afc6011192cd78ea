"""ONNX adapters against tiny stand-in graphs with the real exports' signatures (no weights)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from delta import DeltaError
from delta.preprocess.onnx_models import (
    CLOTH_CLASSES,
    FACE_PARSING_CLASSES,
    IMAGENET_MEAN,
    IMAGENET_STD,
    MODNet,
    ClothSegmentation,
    FaceParsing,
    RobustVideoMatting,
    clothing_mask,
    face_skin_mask,
    hair_mask,
    modnet_size,
    open_session,
)

F32, F16 = TensorProto.FLOAT, TensorProto.FLOAT16


def _save(graph: onnx.GraphProto, path: Path) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def _const(name: str, value) -> onnx.NodeProto:
    return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(np.asarray(value, np.float32), name))


def rvm_graph(path: Path, elem: int = F32, src_name: str = "src") -> Path:
    """RVM signature; pha = clip(mean_c(src) * downsample_ratio + 0.1 * sum(r1i)), rKo = rKi + K."""
    nodes = [_const("one_tenth", 0.1), _const("zero", 0.0), _const("one", 1.0)]
    cast = lambda x, to: helper.make_node("Cast", [x], [f"{x}_{to}"], to=to)  # noqa: E731
    nodes += [cast(src_name, F32)] + [cast(f"r{k}i", F32) for k in range(1, 5)]
    nodes += [
        helper.make_node("Identity", [src_name], ["fgr"]),
        helper.make_node("ReduceMean", [f"{src_name}_{F32}"], ["grey"], axes=[1], keepdims=1),
        helper.make_node("Mul", ["grey", "downsample_ratio"], ["scaled"]),
        helper.make_node("ReduceSum", [f"r1i_{F32}"], ["r1sum"], keepdims=0),
        helper.make_node("Mul", ["r1sum", "one_tenth"], ["offset"]),
        helper.make_node("Add", ["scaled", "offset"], ["raw"]),
        helper.make_node("Clip", ["raw", "zero", "one"], ["pha_f"]),
        helper.make_node("Cast", ["pha_f"], ["pha"], to=elem),
    ]
    for k in range(1, 5):
        nodes += [
            _const(f"inc{k}", float(k)),
            helper.make_node("Add", [f"r{k}i_{F32}", f"inc{k}"], [f"r{k}o_f"]),
            helper.make_node("Cast", [f"r{k}o_f"], [f"r{k}o"], to=elem),
        ]
    img = lambda n, c: helper.make_tensor_value_info(n, elem, ["B", c, "H", "W"])  # noqa: E731
    state = lambda n: helper.make_tensor_value_info(n, elem, ["b", "c", "h", "w"])  # noqa: E731
    inputs = [img(src_name, 3)] + [state(f"r{k}i") for k in range(1, 5)]
    inputs.append(helper.make_tensor_value_info("downsample_ratio", F32, [1]))
    outputs = [img("fgr", 3), img("pha", 1)] + [state(f"r{k}o") for k in range(1, 5)]
    return _save(helper.make_graph(nodes, "rvm_standin", inputs, outputs), path)


def modnet_graph(path: Path, rank: int = 4) -> Path:
    """MODNet signature; output = mean_c(input * 0.5 + 0.5), i.e. the grey value in [0, 1]."""
    nodes = [
        _const("half", 0.5),
        helper.make_node("Mul", ["input", "half"], ["a"]),
        helper.make_node("Add", ["a", "half"], ["b"]),
        helper.make_node("ReduceMean", ["b"], ["output"], axes=[1], keepdims=1),
    ]
    dims = [1, 3, "h", "w"][:rank]
    out_dims = [1, 1, "h", "w"][:rank]
    graph = helper.make_graph(
        nodes,
        "modnet_standin",
        [helper.make_tensor_value_info("input", F32, dims)],
        [helper.make_tensor_value_info("output", F32, out_dims)],
    )
    return _save(graph, path)


def parser_graph(path: Path, classes: int, rgb_class: tuple[int, int, int], size: int, extra_outputs: int) -> Path:
    """A 1x1 conv that un-normalises ImageNet input: logit[rgb_class[c]] = rgb[c] / 255, logit[0] = 0.5.

    So black -> 0 and a saturated primary colour -> its class in ``rgb_class``.
    """
    w = np.zeros((classes, 3, 1, 1), np.float32)
    b = np.zeros(classes, np.float32)
    b[0] = 0.5
    for c, k in enumerate(rgb_class):
        w[k, c, 0, 0], b[k] = IMAGENET_STD[c], IMAGENET_MEAN[c]
    nodes = [helper.make_node("Conv", ["input.1", "w", "b"], ["d0"])]
    nodes += [helper.make_node("Identity", ["d0"], [f"d{i}"]) for i in range(1, extra_outputs + 1)]
    out = [helper.make_tensor_value_info(f"d{i}", F32, [1, classes, size, size]) for i in range(extra_outputs + 1)]
    graph = helper.make_graph(
        nodes,
        "parser_standin",
        [helper.make_tensor_value_info("input.1", F32, [1, 3, size, size])],
        out,
        initializer=[numpy_helper.from_array(w, "w"), numpy_helper.from_array(b, "b")],
    )
    return _save(graph, path)


def quadrants(h: int = 40, w: int = 60) -> np.ndarray:
    """Black / red on top, green / blue below."""
    img = np.zeros((h, w, 3), np.uint8)
    img[: h // 2, w // 2 :, 0] = 255
    img[h // 2 :, : w // 2, 1] = 255
    img[h // 2 :, w // 2 :, 2] = 255
    return img


def check_quadrants(labels: np.ndarray, expected: tuple[int, int, int, int], margin: int = 2) -> None:
    h, w = labels.shape
    blocks = [
        labels[: h // 2 - margin, : w // 2 - margin],
        labels[: h // 2 - margin, w // 2 + margin :],
        labels[h // 2 + margin :, : w // 2 - margin],
        labels[h // 2 + margin :, w // 2 + margin :],
    ]
    for block, cls in zip(blocks, expected):
        assert (block == cls).all(), (cls, np.unique(block))


def grey(h: int, w: int, value: int) -> np.ndarray:
    return np.full((h, w, 3), value, np.uint8)


# --- RVM ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("elem", [F32, F16])
def test_rvm_carries_states_and_resets(tmp_path, elem):
    rvm = RobustVideoMatting(rvm_graph(tmp_path / "rvm.onnx", elem), downsample_ratio=0.5)
    frame = grey(8, 6, 51)  # grey 0.2 -> alpha 0.1 + 0.1 * (calls so far)
    for call in range(3):
        alpha = rvm(frame)
        assert alpha.shape == (8, 6) and alpha.dtype == np.float32
        np.testing.assert_allclose(alpha, 0.1 + 0.1 * call, atol=2e-3)
    for k, state in enumerate(rvm.states, start=1):
        np.testing.assert_allclose(state, 3 * k)  # three calls of rKo = rKi + K
    rvm.reset()
    assert all((s == 0).all() and s.shape == (1, 1, 1, 1) for s in rvm.states)
    np.testing.assert_allclose(rvm(frame), 0.1, atol=2e-3)


def test_rvm_auto_downsample_ratio(tmp_path):
    rvm = RobustVideoMatting(rvm_graph(tmp_path / "rvm.onnx"))
    assert rvm.ratio(1024, 768) == 0.5 and rvm.ratio(768, 1024) == 0.5 and rvm.ratio(300, 200) == 1.0
    np.testing.assert_allclose(rvm(grey(1024, 768, 102)), 0.4 * 0.5, atol=1e-5)  # fed ratio 0.5
    np.testing.assert_allclose(rvm(grey(100, 80, 102)), 0.4, atol=1e-5)  # new size: states reset, ratio 1
    np.testing.assert_allclose(rvm(grey(100, 80, 102)), 0.5, atol=1e-5)  # same size: state carried
    with pytest.raises(DeltaError, match="downsample_ratio"):
        RobustVideoMatting(tmp_path / "rvm.onnx", downsample_ratio=2.0)


def test_rvm_wrong_input_name(tmp_path):
    path = rvm_graph(tmp_path / "renamed.onnx", src_name="input")
    with pytest.raises(DeltaError) as err:
        RobustVideoMatting(path)
    msg = str(err.value)
    assert str(path) in msg and "src (rank 4)" in msg and "input (B, 3, H, W)" in msg


# --- MODNet ------------------------------------------------------------------------------------


def test_modnet_size():
    assert modnet_size(300, 200) == (768, 512)
    assert modnet_size(250, 180) == (704, 512)
    assert modnet_size(1080, 1920) == (512, 896)


@pytest.mark.parametrize("hw", [(300, 200), (250, 180), (90, 160)])
def test_modnet_matte_and_fed_shape(tmp_path, hw):
    model = MODNet(modnet_graph(tmp_path / "modnet.onnx"))
    fed = []
    run = model.session.run

    class Recorder:
        def run(self, names, feed):
            fed.append(feed["input"].shape)
            return run(names, feed)

    model.session = Recorder()
    h, w = hw
    img = grey(h, w, 153)
    img[:, : w // 2] = 0
    alpha = model(img)
    assert alpha.shape == (h, w) and alpha.dtype == np.float32
    np.testing.assert_allclose(alpha[:, : w // 2 - 2], 0.0, atol=1e-5)
    np.testing.assert_allclose(alpha[:, w // 2 + 2 :], 0.6, atol=1e-5)
    (shape,) = fed
    assert shape[:2] == (1, 3) and shape[2] % 32 == 0 and shape[3] % 32 == 0 and min(shape[2:]) == 512


def test_modnet_wrong_rank(tmp_path):
    path = modnet_graph(tmp_path / "modnet3.onnx", rank=3)
    with pytest.raises(DeltaError, match=r"input \(rank 4\).*found input \(1, 3, h\)"):
        MODNet(path)


# --- parsers -----------------------------------------------------------------------------------


def test_cloth_segmentation_quadrants(tmp_path):
    seg = ClothSegmentation(parser_graph(tmp_path / "u2net_cloth_seg.onnx", 4, (1, 2, 3), 768, 6))
    assert seg.size == 768 and len(CLOTH_CLASSES) == 4
    labels = seg(quadrants())
    assert labels.shape == (40, 60) and labels.dtype == np.uint8
    check_quadrants(labels, (0, 1, 2, 3))
    mask = clothing_mask(labels)
    assert mask.dtype == bool and not mask[:18, :28].any() and mask[:18, 32:].all()


def test_face_parsing_quadrants(tmp_path):
    hair, skin, hat = 17, 1, 18
    parse = FaceParsing(parser_graph(tmp_path / "bisenet.onnx", 19, (hair, skin, hat), 512, 2))
    assert len(FACE_PARSING_CLASSES) == 19 and FACE_PARSING_CLASSES[17] == "hair"
    labels = parse(quadrants(50, 30))
    assert labels.shape == (50, 30)
    check_quadrants(labels, (0, hair, skin, hat))
    assert hair_mask(labels)[:23, 17:].all() and not hair_mask(labels)[27:].any()
    assert face_skin_mask(labels)[27:, :13].all() and not face_skin_mask(labels)[:23].any()
    assert face_skin_mask(np.arange(19)).nonzero()[0].tolist() == [1, 2, 3, 4, 5, 7, 8, 10, 11, 12, 13]


def test_parser_static_size_mismatch(tmp_path):
    path = parser_graph(tmp_path / "small.onnx", 19, (17, 1, 18), 256, 0)
    assert FaceParsing(path).size == 256  # taken from the model
    with pytest.raises(DeltaError, match="small.onnx.*expected \\(1, 3, 512, 512\\)"):
        FaceParsing(path, size=512)


# --- files and frames --------------------------------------------------------------------------


def test_missing_and_corrupt_files(tmp_path):
    missing = tmp_path / "nope.onnx"
    with pytest.raises(DeltaError, match="ONNX model not found: .*nope.onnx.*matting.rvm"):
        open_session(missing, {"src": 4}, config_key="matting.rvm")
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(DeltaError, match="corrupt.onnx"):
        MODNet(corrupt)
    with pytest.raises(DeltaError, match="ONNX model not found"):
        ClothSegmentation(tmp_path)  # a directory


def test_output_count_and_extra_inputs(tmp_path):
    path = modnet_graph(tmp_path / "modnet.onnx")
    with pytest.raises(DeltaError, match="at least 2 ONNX output"):
        open_session(path, {"input": 4}, expected_outputs=2)
    with pytest.raises(DeltaError, match="expected src"):
        open_session(path, {"src": 4})
    assert open_session(path, {"*": 4}, threads=2).get_inputs()[0].name == "input"


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((8, 8, 3), np.float32),
        np.zeros((8, 8, 4), np.uint8),
        np.zeros((8, 8), np.uint8),
        np.zeros((0, 8, 3), np.uint8),
        [[0, 0, 0]],
    ],
)
def test_bad_frames(tmp_path, bad):
    models = [
        RobustVideoMatting(rvm_graph(tmp_path / "rvm.onnx")),
        MODNet(modnet_graph(tmp_path / "m.onnx")),
        FaceParsing(parser_graph(tmp_path / "f.onnx", 19, (17, 1, 18), 64, 0)),
    ]
    for model in models:
        with pytest.raises(DeltaError, match=r"uint8 array of shape \(H, W, 3\)|empty frame"):
            model(bad)
