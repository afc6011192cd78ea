"""An exterior in layers (``training.layers: split``): clothing and hair each their own NeRF, trained,
saved, loaded back and carried into stage 2; one NeRF where the capture does not show both."""

import dataclasses

import pandas as pd
import pytest
import torch

from delta.data.frames import ByteFrames, load_frames
from delta.fields.networks import LayeredNeRF, NeRFField
from delta.io import load_state
from delta.models.image import render_image
from delta.training.presets import resolve
from delta.training.run import _scope, exterior_layers, load_trained, run_stage
from tests.conftest import TINY_STAGE1

pytestmark = pytest.mark.slow
SPLIT = {"layers": "split"}
STAGE2 = {"semantic": "none", "stage2": {"iterations": 2, "rays": 128, "checkpoint_every": 2, "preview_every": 0}}


@pytest.fixture(scope="module")
def layered(tiny_training, tmp_path_factory):
    """A stage 1 of the loose subject (a dress and long hair) trained in layers: (inputs, its folder)."""
    inputs, out = tiny_training["loose"], tmp_path_factory.mktemp("layers")
    run_stage(1, inputs["record"], inputs["body"], inputs["init"], str(out / "s1"), "fast", [TINY_STAGE1, SPLIT])
    return inputs, out


def test_clothing_and_hair_train_as_layers_and_load_back(layered, tmp_path):
    inputs, tmp_path = layered[0], layered[1]
    state = load_state(tmp_path / "s1" / "model.pt")
    assert state["layers"] == ["clothing", "hair"]
    assert any(k.startswith("nerf.layers.hair.") for k in state["model"])
    losses = pd.read_csv(tmp_path / "s1" / "losses.csv")
    assert losses["exterior_layers"].notna().all() and (losses["exterior_layers"] > 0).all()
    assert losses["layer_shares"].notna().all() and (losses["layer_shares"] >= 0).all()  # the presets' weight
    for name in ("clothing", "hair"):  # each layer's opacity on its own mask's rays: a readout in [0, 1]
        seen = losses[f"seen_{name}"].dropna()
        assert len(seen) and ((seen >= 0) & (seen <= 1 + 1e-6)).all()
    tr = load_trained(tmp_path / "s1" / "model.pt", inputs["record"], inputs["body"])
    assert isinstance(tr.model.nerf, LayeredNeRF) and tr.model.nerf.names == ("clothing", "hair")
    # the head may carry clothing (the presets' clothing_on_head: yes), in the file and loaded back
    assert state["clothing_off_head"] is False and not tr.model.spec.clothing_off_head
    assert tr.model.nerf.layers["clothing"].barred_carriers is None
    img = render_image(tr.model, int(tr.data.train[0]))
    assert bool(torch.isfinite(img["rgb"]).all()) and {"layer_clothing", "layer_hair"} <= set(img)
    torch.testing.assert_close(img["layer_clothing"] + img["layer_hair"], img["nerf_mask"], rtol=0, atol=1e-5)
    # stage 2 starts from the layered stage 1 (the layers travel with the model, not the settings)
    run_stage(2, inputs["record"], inputs["body"], str(tmp_path / "s1" / "model.pt"), str(tmp_path / "s2"), "fast",
              [TINY_STAGE1, SPLIT, STAGE2])  # fmt: skip
    tr2 = load_trained(tmp_path / "s2" / "model.pt", inputs["record"], inputs["body"])
    assert isinstance(tr2.model.nerf, LayeredNeRF) and tr2.model.deformation is not None
    for k, v in tr.model.nerf.state_dict().items():  # trained on: changed, same layout
        assert tr2.model.nerf.state_dict()[k].shape == v.shape


def test_one_nerf_unless_split_and_both_are_seen(tiny_training):
    inputs = tiny_training["loose"]
    st = resolve("fast", TINY_STAGE1, SPLIT)
    data = load_frames(inputs["record"], st.resolution, st.background, st.box_margin, hair=True)
    assert data.hair is not None and data.hair.total(slice(None)) > 0
    assert bool((data.hair.bytes <= data.exterior.bytes).all())  # hair is part of the exterior
    assert exterior_layers(st, data) == ("clothing", "hair")
    assert exterior_layers(resolve("fast", TINY_STAGE1), data) == ()  # the default: one NeRF
    no_hair = dataclasses.replace(data, hair=ByteFrames(torch.zeros_like(data.hair.bytes)))
    assert exterior_layers(st, no_hair) == ()
    all_hair = dataclasses.replace(data, hair=data.exterior)  # nothing left for clothing
    assert exterior_layers(st, all_hair) == ()
    assert load_frames(inputs["record"], 32).hair is None


def test_a_one_nerf_model_loads_as_before(tiny_trained):
    inputs = tiny_trained["loose"]
    state = load_state(inputs["model"])
    tr = load_trained(inputs["model"], inputs["record"], inputs["body"])
    assert isinstance(tr.model.nerf, NeRFField) and state["layers"] == []
    assert _scope({"capture": "full", "frozen_joints": []})["layers"] == []  # a file written before layers


def test_each_layer_is_scored_against_its_own_mask(layered):
    from delta.data.frames import load_full_frames
    from delta.eval.evaluate import evaluate, pick_frames
    from delta.eval.settings import EvalSettings
    from delta.metrics import iou
    from delta.models.image import full_view

    inputs, out = layered
    tr = load_trained(out / "s1" / "model.pt", inputs["record"], inputs["body"])
    df = evaluate(
        tr, inputs["record"], EvalSettings(splits=("test_view",), max_frames=1, refine_steps=0, supersample=1)
    )
    assert {"clothing_layer_iou", "hair_layer_iou"} <= set(df.columns)
    frame = pick_frames(tr.data.split, ("test_view",), 1)[0][0]
    full = load_full_frames(inputs["record"], [frame], tr.settings.background)
    img = render_image(tr.model, frame, view=full_view(full, tr.model.resolution), soft_silhouette=False)
    for name in ("clothing", "hair"):  # the same IoU, taken here from the render and the record's mask
        assert df[f"{name}_layer_iou"].iloc[0] == pytest.approx(iou(img[f"layer_{name}"] > 0.5, full.parts[name][0]))


def test_each_layers_opacity_on_its_own_masks_rays_and_a_dead_layer_named():
    from delta.training.run import dead_layers
    from delta.training.trainer import layers_seen

    masks = torch.tensor([[0.9, 0.05], [0.1, 0.02], [0.0, 0.0]])  # (R, L) clothing, hair
    exterior, hair = torch.tensor([1.0, 1.0, 0.0]), torch.tensor([0.0, 1.0, 0.0])
    seen = layers_seen(masks, ("clothing", "hair"), exterior, hair)
    torch.testing.assert_close(seen["seen_clothing"], torch.tensor(0.9))  # ray 0 alone is the clothing's
    torch.testing.assert_close(seen["seen_hair"], torch.tensor(0.02))  # ray 1 alone is the hair's
    none = layers_seen(masks, ("clothing", "hair"), exterior, torch.zeros(3))
    assert bool(torch.isnan(none["seen_hair"])) and layers_seen(masks, ("clothing", "hair"), exterior, None) == {}
    assert dead_layers({"clothing": 0.9, "hair": 0.02}) == ["hair"]
    assert dead_layers({"clothing": 0.9, "hair": float("nan")}) == []  # never met: not judged
