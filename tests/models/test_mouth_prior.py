"""The mouth's inside starts shaded: a fresh avatar's albedo there, a body without a mouth, and trained files
written before the prior (format 2) rendering as they were trained."""

import dataclasses

import pytest
import torch

from delta.body.model import REGION
from delta.models.avatar import HybridAvatar, mouth_prior
from delta.training.presets import resolve
from delta.training.run import _scope, load_trained, scoped
from tests.test_extremes import blob_body
from tests.training.test_expressions import init

SKIN = torch.tensor([0.8, 0.6, 0.5])


def fresh(body, shade=None) -> HybridAvatar:
    st = resolve(
        "fast", {"render": {"samples": 8}} if shade is None else {"render": {"samples": 8}, "mouth_shade": shade}
    )
    return HybridAvatar(body, dataclasses.replace(st.avatar, nerf=None), init(), SKIN, torch.ones(3), 32)


def test_a_fresh_avatar_starts_its_mouth_inside_at_the_shade_of_its_skin():
    body = blob_body()
    mouth = body.regions == REGION["mouth"]
    assert 0 < int(mouth.sum()) < body.num_vertices
    model = fresh(body)
    shade = resolve("fast").avatar.mouth_shade
    assert 0 < shade < 1
    with torch.no_grad():
        albedo = model.albedo()
    torch.testing.assert_close(albedo[mouth], (shade * SKIN).expand(int(mouth.sum()), 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(albedo[~mouth], SKIN.expand(int((~mouth).sum()), 3), atol=1e-5, rtol=0)
    # a setting of the user's: a darker inside; 1 is the skin everywhere and no prior at all
    with torch.no_grad():
        dark = fresh(body, 0.1).albedo()
    torch.testing.assert_close(dark[mouth], (0.1 * SKIN).expand(int(mouth.sum()), 3), atol=1e-5, rtol=0)
    # a shade a channel (the capture's own inside, a scene decision): red kept, green and blue darker
    with torch.no_grad():
        red = fresh(body, [0.5, 0.2, 0.1]).albedo()
    want = torch.tensor([0.5, 0.2, 0.1]) * SKIN
    torch.testing.assert_close(red[mouth], want.expand(int(mouth.sum()), 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(red[~mouth], SKIN.expand(int((~mouth).sum()), 3), atol=1e-5, rtol=0)
    plain = fresh(body, 1.0)
    assert plain.albedo_field.prior is None
    assert fresh(body, [1, 1, 1]).albedo_field.prior is None
    with torch.no_grad():
        torch.testing.assert_close(plain.albedo(), SKIN.expand(body.num_vertices, 3), atol=1e-5, rtol=0)


def test_a_body_without_a_mouth_gets_no_prior_and_the_prior_is_not_saved():
    body = blob_body()
    mouthless = dataclasses.replace(body, regions=torch.where(body.regions == REGION["mouth"], REGION["face"],
                                                              body.regions))  # fmt: skip
    assert mouth_prior(mouthless, SKIN, 0.3) is None
    assert fresh(mouthless).albedo_field.prior is None
    model = fresh(body)
    assert model.albedo_field.prior is not None
    assert not any("prior" in k for k in model.state_dict())


def test_the_prior_is_a_fixed_start_training_moves_away_from():
    """The inside's colour is learned where a frame shows it: the prior is a fixed addition, so the field's
    gradient there is the sigmoid's slope at the shaded colour (a fresh field's raw output is its bias)."""
    body = blob_body()
    model = fresh(body)
    assert not model.albedo_field.prior.requires_grad
    mouth = body.regions == REGION["mouth"]
    model.albedo()[mouth].sum().backward()
    c = resolve("fast").avatar.mouth_shade * SKIN
    torch.testing.assert_close(model.albedo_field.head.out.bias.grad, int(mouth.sum()) * c * (1 - c), rtol=1e-4, atol=0)


def test_stage_two_keeps_the_shade_stage_one_was_trained_with():
    spec = resolve("fast").avatar
    for written, kept in ((0.5, 0.5), ([0.5, 0.2, 0.1], (0.5, 0.2, 0.1)), (None, 1.0)):  # a file's own shade;
        # a file without one: the skin's
        settings = {} if written is None else {"mouth_shade": written}
        scope = _scope({"capture": "upper", "frozen_joints": [], "settings": settings})
        assert scope["mouth_shade"] == kept and scoped(spec, scope).mouth_shade == kept
    assert scoped(spec, {"capture": "full", "frozen_joints": []}).mouth_shade == spec.mouth_shade  # a fresh stage 1


@pytest.mark.parametrize("written_before", [False, True])
def test_a_trained_file_renders_its_mouth_as_it_was_trained(tmp_path, tiny_trained, written_before):
    """A model.pt of format 2 predates the prior: loaded, its mouth's inside is the field's own colour;
    the same weights in format 3 add the prior there and nowhere else."""
    src = tiny_trained["tight"]
    path = src["model"]
    if written_before:
        state = torch.load(path, weights_only=True)
        settings = {k: v for k, v in state["settings"].items() if k != "mouth_shade"}
        path = tmp_path / "model.pt"
        torch.save(dict(state, format=2, settings=settings), path)
    new = load_trained(src["model"], src["record"], src["body"]).model
    loaded = load_trained(path, src["record"], src["body"]).model
    mouth = loaded.body.regions == REGION["mouth"]
    assert int(mouth.sum()) > 0
    with torch.no_grad():
        a_new, a_loaded = new.albedo(), loaded.albedo()
    if not written_before:
        torch.testing.assert_close(a_loaded, a_new)
        return
    assert loaded.albedo_field.prior is None and loaded.spec.mouth_shade == 1.0
    logit = torch.logit
    shift = logit(a_new.double()) - logit(a_loaded.double())
    prior = new.albedo_field.prior.double()
    torch.testing.assert_close(shift, prior, atol=1e-4, rtol=0)
    assert float(prior[mouth].abs().min()) > 0.5 and float(prior[~mouth].abs().max()) == 0.0


@pytest.mark.parametrize("bad", [[0.5, 0.2], [0.5, 1.5, 0.1], [0.5, float("nan"), 0.1], "dark", -0.1, True])
def test_a_shade_is_a_number_or_three_each_in_zero_to_one(bad):
    from delta import DeltaError

    with pytest.raises(DeltaError, match="mouth_shade"):
        resolve("fast", {"mouth_shade": bad})
    assert resolve("fast", {"mouth_shade": [0.5, 0.2, 0.1]}).avatar.mouth_shade == (0.5, 0.2, 0.1)
