"""Shape edits: the phenotype estimated from a generated subject's β is the generator's own, an edit lands on the
β of the edited phenotype, bad edits are named, and ``delta reshape`` runs end to end."""

import json

import cv2
import numpy as np
import pytest
import torch

from delta import DeltaError
from delta.applications.reshape import edit_betas, estimate_phenotype, split_edit
from delta.body.anny_convert import ShapeSpace, phenotype_betas
from delta.cli import main

LABELS = ["gender", "age", "muscle", "weight", "height", "proportions"]


@pytest.fixture(scope="module")
def space(anny_files):
    return ShapeSpace.load(anny_files["shape_space"])


@pytest.mark.slow
def test_the_phenotype_of_a_generated_shape_is_recovered(space, anny_model):
    """β of a known phenotype (the generator's own function) -> the estimate gives that phenotype back."""
    truth = {"gender": 0.85, "age": 0.35, "muscle": 0.6, "weight": 0.3, "height": 0.7, "proportions": 0.5}
    betas = phenotype_betas(space, anny_model, truth)
    est = estimate_phenotype(space, anny_model, betas)
    np.testing.assert_allclose(est.numpy(), [truth[k] for k in space.phenotype_labels], atol=0.03)


@pytest.mark.slow
def test_an_edit_lands_on_the_edited_phenotypes_shape_and_keeps_the_rest(space, anny_model):
    """Editing weight turns β(p) into β(p with that weight); a coefficient edit sets that coefficient alone."""
    p = {"gender": 0.3, "age": 0.6, "weight": 0.4}
    betas = phenotype_betas(space, anny_model, p)
    new, about = edit_betas(betas, {"weight": 0.9}, space, anny_model)
    want = phenotype_betas(space, anny_model, {**p, "weight": 0.9})
    assert (want - betas).abs().max() > 0.3  # the edit changes the shape (by 0.45 σ here) ...
    assert (new - want).abs().max() < 0.05  # ... to the edited phenotype's
    assert about["edited"]["weight"] == 0.9 and abs(about["estimated"]["weight"] - 0.4) < 0.03
    coeff, _ = edit_betas(betas, {"beta2": -1.5})
    assert coeff[2] == -1.5 and torch.equal(torch.cat([coeff[:2], coeff[3:]]), torch.cat([betas[:2], betas[3:]]))
    moved, _ = edit_betas(betas, {"beta2": "+0.5"})
    assert moved[2] == pytest.approx(float(betas[2]) + 0.5)
    # a change: weight 0.4 + 0.3 -> the β of weight 0.7
    changed, about = edit_betas(betas, {"weight": "+0.3"}, space, anny_model)
    assert (changed - phenotype_betas(space, anny_model, {**p, "weight": 0.7})).abs().max() < 0.05
    assert abs(about["edited"]["weight"] - 0.7) < 0.03


@pytest.mark.parametrize("edit, message", [
    ({}, "the shape edit is empty"),
    ({"wieght": 0.5}, "shape edit 'wieght': unknown label"),
    ({"weight": 1.5}, "outside Anny's phenotype range"),
    ({"weight": float("nan")}, "not a finite number"),
    ({"beta40": 1.0}, "has 8 shape coefficients"),
    ({"weight": "0.3"}, "neither a number nor a signed change"),
    ({"weight": "+x"}, "neither a number nor a signed change"),
    ({"weight": "+1.5"}, "outside Anny's phenotype range"),
])  # fmt: skip
def test_bad_edits_are_named(edit, message):
    with pytest.raises(DeltaError, match=message):
        split_edit(edit, LABELS, 8)


def test_phenotype_labels_need_the_shape_space():
    with pytest.raises(DeltaError, match="phenotype labels need Anny's shape space"):
        split_edit({"weight": 0.5}, None, 10)


@pytest.mark.slow
def test_the_reshape_command_writes_its_outputs(tiny_trained, tmp_path):
    tight = tiny_trained["tight"]
    out = tmp_path / "reshape"
    code = main(["reshape", "--model", tight["model"], "--record", tight["record"], "--body", tight["body"],
                 "--edit", '{"beta0": -1.0}', "--out", str(out), "--turntable-frames", "2"])  # fmt: skip
    assert code == 0
    about = json.loads((out / "reshape.json").read_text())
    assert about["betas_after"][0] == -1.0 and about["betas_after"][1:] == about["betas_before"][1:]
    W, H = (int(x) for x in about["resolution"].split("x"))
    image = cv2.imread(str(out / "reshaped.png"))
    assert image.shape == (H, 3 * W, 3)
    assert np.abs(image[:, W : 2 * W].astype(int) - image[:, 2 * W :].astype(int)).max() > 0  # the shape changed
    assert (out / "body_canonical.ply").stat().st_size > 0
    code = main(["reshape", "--model", tight["model"], "--record", tight["record"], "--body", tight["body"],
                 "--edit", '{"weight": 0.8}', "--out", str(tmp_path / "x")])  # fmt: skip
    assert code == 2  # phenotype labels without the shape space: said, not guessed
