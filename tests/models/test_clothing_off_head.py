"""A clothing layer that the head does not carry: a collar under a chin that tilts back stays with the chest."""

import dataclasses

import pytest
import torch

from delta.body.lbs import lbs

from delta.body.model import load_body_model
from delta.body.parts import head_vertices
from delta.data.frames import load_frames
from delta.deformers import knn as deformer
from delta.fields.networks import LayeredNeRF
from delta.fields.spec import FieldSpec
from delta.models.init import load_init
from delta.models.layer_support import Confined, Support
from delta.scene.framing import clothing_on_head
from delta.training.presets import resolve
from delta.training.run import build_avatar, clothing_off_head
from tests.conftest import TINY_STAGE1


def test_a_layer_has_no_density_where_a_barred_vertex_carries_the_point():
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    torch.manual_seed(0)
    nerf = LayeredNeRF(FieldSpec(max_res=16, levels=2), box, ("clothing", "hair"), density_bias=1.0)
    x = torch.rand(500, 3) * 2 - 1
    carriers = torch.randint(0, 10, (500,))
    rgb0, sigma0, layers0 = nerf.with_layers(x)
    nerf.layers["clothing"].barred_carriers = torch.arange(10) < 4  # vertices 0-3 carry no clothing
    rgb, sigma, layers = nerf.with_layers(x, carriers)
    barred = carriers < 4
    assert bool((layers[barred, 0] == 0).all()) and torch.equal(layers[~barred, 0], layers0[~barred, 0])
    assert torch.equal(layers[:, 1], layers0[:, 1])  # the hair layer as it was
    torch.testing.assert_close(sigma, layers.sum(-1))
    torch.testing.assert_close(rgb[barred], nerf.layers["hair"](x[barred])[0])  # the hair's colour alone
    assert torch.equal(rgb[~barred], rgb0[~barred]) and torch.equal(nerf.with_layers(x)[2], layers0)
    assert "layers.clothing.barred_carriers" not in nerf.state_dict()  # derived from the body, not saved
    # a layer confined to its support (worn by another body) keeps its bar
    everywhere = Support(box[0], 1.0, torch.ones(2, 2, 2, dtype=torch.bool))
    worn = LayeredNeRF.of({"clothing": Confined(nerf.layers["clothing"], everywhere), "hair": nerf.layers["hair"]})
    assert torch.equal(worn.with_layers(x, carriers)[2], layers)


def test_the_head_is_the_head_and_not_the_neck_or_hands(anny_files):
    body = load_body_model(anny_files["body"])
    head = head_vertices(body)
    assert bool(head[body.v_template[:, 1].argmax()])  # the crown
    names = body.joint_names
    neck = body.weights[:, [j for j, n in enumerate(names) if n.startswith("neck")]].sum(1) > 0.5
    hands = body.weights[:, body.subtree("wrist.L") | body.subtree("wrist.R")].sum(1) > 0.5
    assert neck.any() and hands.any() and not (head & neck).any() and not (head & hands).any()
    assert 0.05 < float(head.float().mean()) < 0.5


def _loose_in_layers(tiny_training, clothing_on_head: str):
    """The tiny loose subject (a dress, long hair) set up for training in layers: settings, frames, body, init."""
    inputs = tiny_training["loose"]
    st = resolve("fast", TINY_STAGE1, {"layers": "split", "clothing_on_head": clothing_on_head})
    data = load_frames(inputs["record"], st.resolution, st.background, st.box_margin, hair=True)
    return st, data, load_body_model(inputs["body"]), load_init(inputs["init"], data)


@pytest.mark.slow
def test_a_collar_under_a_chin_that_tilts_back_stays_with_the_chest(tiny_training):
    st, data, body, init = _loose_in_layers(tiny_training, "no")
    model = build_avatar(body, st, init, data, 1, "cpu")
    free = build_avatar(body, dataclasses.replace(st, clothing_on_head="yes"), init, data, 1, "cpu")
    assert model.spec.clothing_off_head and model.nerf.layers["clothing"].barred_carriers is not None
    assert model.nerf.layers["hair"].barred_carriers is None
    assert not free.spec.clothing_off_head and free.nerf.layers["clothing"].barred_carriers is None
    for avatar in (model, free):  # the clothing dense everywhere
        torch.nn.init.constant_(avatar.nerf.layers["clothing"].head.out.bias, 3.0)
    # a frame whose head tilts back: a point 2 cm before the chin is the head's, one 2 cm before the upper
    # chest the chest's; rendered as the renderer queries them
    f = int(data.train[0])
    head_joint = body.joint_names.index("head")
    head = head_vertices(body)
    densities = []
    for avatar in (model, free):
        with torch.no_grad():
            avatar.poses[f, head_joint, 0] -= 0.6
            mesh = avatar.posed_mesh(f)[0]
        v = mesh.vertices
        chin = v[head][v[head][:, 2].argmax()]
        below = ~head & (v[:, 1] < chin[1] - 0.2) & (v[:, 1] > chin[1] - 0.35)
        chest = v[below][v[below][:, 2].argmax()]
        points = torch.stack([chin, chest]) + torch.tensor([0.0, 0.0, 0.02])
        d = deformer.deform(mesh.skinning, points, st.avatar.render.k, st.avatar.render.sigma, 0.1)
        assert bool(d.valid.all())
        carried_by_head = head.to(avatar.knn_ids.device)[avatar.knn_ids][d.nearest]
        assert carried_by_head.tolist() == [True, False]
        with torch.no_grad():
            densities.append(avatar.nerf.with_layers(d.canonical, d.nearest)[2])  # (2, layers)
    barred, allowed = densities
    assert barred[0, 0] == 0 and allowed[0, 0] > 1  # no collar at the chin
    assert barred[1, 0] == allowed[1, 0] > 1  # the chest's clothing as it was
    assert torch.equal(barred[:, 1], allowed[:, 1])  # the hair untouched


@pytest.mark.slow
def test_clothing_on_the_head_is_measured_on_the_fitted_heads_pixels(tiny_training):
    st, data, body, init = _loose_in_layers(tiny_training, "auto")
    n = data.resolution

    def share(mask):
        return clothing_on_head(body, init.betas, init.poses, init.transl, init.camera, data.train, n, mask)

    assert share(lambda f: torch.zeros(n, n, dtype=torch.bool)) == 0.0
    assert share(lambda f: torch.ones(n, n, dtype=torch.bool)) == 1.0
    assert share(lambda f: (data.exterior[f] - data.hair[f]) > 0.5) < 0.1  # the dress covers none of the head
    layers = ("clothing", "hair")
    assert clothing_off_head(body, st, init, data, layers)
    assert resolve("fast").clothing_on_head == "yes"  # off in the presets
    assert not clothing_off_head(body, st, init, data, ())  # no clothing layer: nothing to bar
    assert not clothing_off_head(body, dataclasses.replace(st, clothing_on_head="yes"), init, data, layers)
    assert clothing_off_head(body, dataclasses.replace(st, clothing_on_head="no"), init, data, layers)
    hood = dataclasses.replace(data, exterior=data.person)  # clothing wherever the person is: a hood
    assert not clothing_off_head(body, st, init, hood, layers)


def test_an_unknown_clothing_on_head_setting_is_named():
    from delta import DeltaError

    with pytest.raises(DeltaError, match="training.clothing_on_head: 'maybe'"):
        resolve("fast", {"clothing_on_head": "maybe"})


@pytest.mark.slow
@pytest.mark.parametrize("carriage", ["head", "height"])
def test_a_hair_layer_bound_to_the_head_reads_the_head_bound_points(tiny_training, carriage):
    from delta.render.hybrid import _query_points

    st, data, body, init = _loose_in_layers(tiny_training, "yes")
    bound = dataclasses.replace(st, avatar=dataclasses.replace(
        st.avatar, render=dataclasses.replace(st.avatar.render, hair_carriage=carriage, early_cull=False)))  # fmt: skip
    model = build_avatar(body, bound, init, data, 1, "cpu")
    plain = build_avatar(body, st, init, data, 1, "cpu")
    assert model.hair_carriers is not None and plain.hair_carriers is None
    if carriage == "height":  # from the shoulders' joints up to the head's, in the canonical space
        names = body.joint_names
        J = lbs(body, torch.zeros(1, 1), body.canonical_pose[None].float()).joints[0]
        low = float(J[[names.index("upperarm01.L"), names.index("upperarm01.R")], 1].mean())
        assert model.hair_span == pytest.approx((low, float(J[names.index("head"), 1])))
    else:
        assert model.hair_span is None
    f = int(data.train[0])
    with torch.no_grad():
        model.poses[f, body.joint_names.index("head"), 1] += 0.6  # the head turned
        mesh = model.posed_mesh(f)[0]
    assert mesh.skinning.head_index is not None and plain.posed_mesh(f)[0].skinning.head_index is None
    assert mesh.skinning.head_span == model.hair_span
    v, head = mesh.vertices, head_vertices(body)
    # points beside the neck, from the jaw down to the shoulder, 3 cm out to the side
    side = v[head][:, 0].argmax()
    top = v[head][side]
    points = top + torch.stack([torch.tensor([0.03, -0.03 * k, 0.0]) for k in range(6)])
    rs = model.spec.render
    with torch.no_grad():
        at, s, _, layers, _ = _query_points(mesh, points, torch.arange(6), rs, model.nerf, None, None)
        d = deformer.deform(mesh.skinning, points[at], rs.k, rs.sigma, rs.max_dist)
        hair_at = deformer.head_bound(mesh.skinning, points[at], d.canonical, d.distance)
    assert len(at) >= 4
    torch.testing.assert_close(layers[:, 0], model.nerf.layers["clothing"](d.canonical)[1])
    torch.testing.assert_close(layers[:, 1], model.nerf.layers["hair"](hair_at)[1])
    torch.testing.assert_close(s, layers.sum(-1))
    assert float((hair_at - d.canonical).norm(dim=-1).max()) > 0.005  # somewhere the head carries it apart


@pytest.mark.slow
def test_an_unknown_hair_carriage_is_named(tiny_training):
    st, data, body, init = _loose_in_layers(tiny_training, "yes")
    odd = dataclasses.replace(st, avatar=dataclasses.replace(
        st.avatar, render=dataclasses.replace(st.avatar.render, hair_carriage="scalp")))  # fmt: skip
    with pytest.raises(ValueError, match="render.hair_carriage: 'scalp'"):
        build_avatar(body, odd, init, data, 1, "cpu")
