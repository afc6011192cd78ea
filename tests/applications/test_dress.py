"""One avatar's exterior on another's body: the same avatar reproduces itself, an analytic shell follows the new
body's shape and pose, framings that cannot carry an exterior are refused, and ``delta dress`` runs end to end."""

import json

import cv2
import numpy as np
import pytest
import torch
import trimesh

from delta import DeltaError
from delta.applications.dress import check_wearable, confine, put_on
from delta.body.lbs import lbs
from delta.cli import main
from delta.export import lineup
from delta.models.image import View, render_image
from delta.training.run import load_trained
from tests.export.test_export import SHELL, Part, ShellNeRF, layered

pytestmark = pytest.mark.slow


def load(inputs):
    return load_trained(inputs["model"], inputs["record"], inputs["body"])


def test_an_avatar_wearing_its_own_exterior_renders_as_itself(tiny_trained):
    own, twin = load(tiny_trained["tight"]), load(tiny_trained["tight"])
    with torch.no_grad():
        before = [render_image(own.model, f)["rgb"] for f in (0, 3)]
        put_on(own.model, twin.model)
        after = [render_image(own.model, f)["rgb"] for f in (0, 3)]
    for b, a in zip(before, after):
        assert torch.equal(b, a)


def test_the_wearers_mirror_where_no_frame_looked_comes_with_its_whole_exterior_and_none_with_mixed_layers(
    tiny_trained,
):
    from delta.geometry.mirror import MirrorGrid

    body, wearer = load(tiny_trained["tight"]), load(tiny_trained["loose"])
    theirs = MirrorGrid(torch.zeros(3), 0.5, torch.zeros(2, 2, 2))
    body.model.exterior_mirror = MirrorGrid(torch.ones(3), 0.5, torch.ones(2, 2, 2))
    wearer.model.exterior_mirror = theirs
    put_on(body.model, wearer.model)
    assert body.model.exterior_mirror is theirs
    body, wearer = load(tiny_trained["tight"]), load(tiny_trained["loose"])
    layered(body.model, (0.1, 0.2, 0.9), (0.9, 0.9, 0.1))
    layered(wearer.model, (0.9, 0.1, 0.1), (0.1, 0.8, 0.2))
    body.model.exterior_mirror = wearer.model.exterior_mirror = theirs
    put_on(body.model, wearer.model, ["hair"])  # the body keeps its clothing: two trainings' layers
    assert body.model.exterior_mirror is None


def test_worn_hair_is_carried_as_its_own_avatar_carried_it(tiny_trained):
    import dataclasses

    def bound(avatar):
        spec = avatar.model.spec
        avatar.model.spec = dataclasses.replace(spec, render=dataclasses.replace(spec.render, hair_carriage="head"))

    for given, expected in ((["hair"], "head"), (["clothing"], "nearest")):
        body, wearer = load(tiny_trained["tight"]), load(tiny_trained["loose"])
        layered(body.model, (0.1, 0.2, 0.9), (0.9, 0.9, 0.1))
        layered(wearer.model, (0.9, 0.1, 0.1), (0.1, 0.8, 0.2))
        bound(wearer)  # the wearer's hair bound to its head, the body's carried by its nearest vertices
        put_on(body.model, wearer.model, given)
        assert body.model.spec.render.hair_carriage == expected
        assert (body.model.hair_carriers is not None) == (expected == "head")
    body, wearer = load(tiny_trained["tight"]), load(tiny_trained["loose"])
    layered(wearer.model, (0.9, 0.1, 0.1), (0.1, 0.8, 0.2))
    bound(wearer)
    put_on(body.model, wearer.model)  # the whole exterior: the wearer's settings with it
    assert body.model.spec.render.hair_carriage == "head" and body.model.hair_carriers is not None


def inflated_silhouette(model, frame: int, betas: torch.Tensor, view: View) -> np.ndarray:
    """The body of shape ``betas`` in ``frame``'s pose, inflated by SHELL along its normals, projected into ``view``."""
    out = lbs(model.body, betas[None], model.poses[frame : frame + 1], transl=model.transl[frame : frame + 1])
    verts = out.vertices[0].detach().numpy().astype(np.float64)
    faces = model.body.faces.numpy()
    grown = verts + SHELL * trimesh.Trimesh(verts, faces, process=False).vertex_normals
    uv, depth = model.camera(frame).project(torch.from_numpy(grown).float())
    uv = view.from_model(uv).detach().numpy().astype(np.float64)
    depth = depth.detach().numpy() if model.pinhole else np.ones(len(grown))
    return lineup.rasterize(uv, depth, faces, view.height, view.width)


def test_a_shell_exterior_follows_the_new_bodys_shape(tiny_trained):
    """The loose avatar's exterior replaced by a shell SHELL thick around the mean-shape canonical body, put on
    the tight avatar made much broader: the rendered exterior hugs the broad body (inflated by SHELL), not
    the mean-shape body it was made around."""
    body, wearer = load(tiny_trained["tight"]), load(tiny_trained["loose"])
    cano_T, template = wearer.model.canonical_T, wearer.model.body.v_template
    wearer.model.nerf = ShellNeRF((cano_T[..., :3] @ template[..., None]).squeeze(-1) + cano_T[..., 3])
    wearer.model.occupancy = None
    wearer.model.spec.render.samples = 32
    wearer.model.spec.render.max_dist = 0.12
    model = body.model
    with torch.no_grad():
        model.betas.data[:] = 0.0
        model.betas.data[0] = -1.5  # far from the mean shape: a much taller body
    put_on(model, wearer.model)
    n = model.resolution
    view = View(3 * n, 3 * n, (1 / 3, 1 / 3))
    frame = 0
    with torch.no_grad():
        mask = render_image(model, frame, view=view)["nerf_mask"].numpy() > 0.5
        broad = inflated_silhouette(model, frame, model.betas.detach(), view)
        mean = inflated_silhouette(model, frame, torch.zeros_like(model.betas), view)
    assert lineup.iou(broad, mean) < 0.6  # the two bodies differ in view (measured 0.43)
    assert lineup.iou(mask, broad) > 0.88  # measured 0.92 (the shell's ramp and 32 samples a ray blur its edge)
    assert lineup.iou(mask, broad) > lineup.iou(mask, mean) + 0.3


def test_a_full_body_exterior_is_refused_on_an_upper_body_avatar(tiny_trained):
    body, wearer = load(tiny_trained["tight"]), load(tiny_trained["loose"])
    body.model.modelled[body.model.body.v_template[:, 1] < 0] = False  # as an 'upper' capture models it
    with pytest.raises(DeltaError, match="an upper-body exterior goes onto a full body, not the reverse"):
        check_wearable(body.model, wearer.model)
    check_wearable(wearer.model, load(tiny_trained["tight"]).model)  # the other way round is fine
    wearer.model.nerf = None
    with pytest.raises(DeltaError, match="has no exterior"):
        check_wearable(load(tiny_trained["tight"]).model, wearer.model)


def test_the_dress_command_writes_its_outputs(tiny_trained, tmp_path):
    tight, loose = tiny_trained["tight"], tiny_trained["loose"]
    out = tmp_path / "dress"
    code = main(["dress", "--model", tight["model"], "--record", tight["record"], "--wearer-model", loose["model"],
                 "--wearer-record", loose["record"], "--body", tight["body"], "--out", str(out),
                 "--turntable-frames", "3"])  # fmt: skip
    assert code == 0
    about = json.loads((out / "dress.json").read_text())
    W, H = (int(x) for x in about["resolution"].split("x"))
    image = cv2.imread(str(out / "dressed.png"))
    assert image.shape == (H, 3 * W, 3)
    assert about["turntable_frames"] == 3 and about["body_capture"] == about["wearer_capture"] == "full"
    video = cv2.VideoCapture(str(out / "turntable.mp4"))
    assert video.get(cv2.CAP_PROP_FRAME_COUNT) == 3
    video.release()
    assert main(["dress", "--model", tight["model"], "--record", tight["record"], "--wearer-model", str(tmp_path / "x.pt"),
                 "--wearer-record", loose["record"], "--body", tight["body"], "--out", str(out)]) == 2  # fmt: skip


def test_hair_moves_alone_and_the_body_keeps_its_own_clothing(tiny_trained):
    """Both avatars in layers: the body avatar wearing the other's hair keeps its own clothing layer (the same
    module), takes the other's hair layer, and renders its own clothing colour below the neck and the
    other's hair colour above it; a wearer of one NeRF has no layer to give."""
    body, wearer = load(tiny_trained["tight"]), load(tiny_trained["loose"])
    layered(body.model, (0.1, 0.2, 0.9), (0.9, 0.9, 0.1))  # blue clothing, yellow hair
    layered(wearer.model, (0.9, 0.1, 0.1), (0.1, 0.8, 0.2))  # red clothing, green hair
    own_clothing, their_hair = body.model.nerf.layers["clothing"], wearer.model.nerf.layers["hair"]
    put_on(body.model, wearer.model, ["hair"])
    nerf = body.model.nerf
    assert nerf.names == ("clothing", "hair") and body.model.spec.layers == ("clothing", "hair")
    assert nerf.layers["clothing"] is own_clothing and nerf.layers["hair"] is their_hair
    assert body.model.deformation is None and body.model.occupancy is None  # two trainings' layers: rigid
    frame = 0
    with torch.no_grad():
        img = render_image(body.model, frame)
    seen = img["nerf_mask"] > 0.9
    colour = img["nerf"][seen]
    assert int(seen.sum()) > 20
    blue, green = torch.tensor([0.1, 0.2, 0.9]), torch.tensor([0.1, 0.8, 0.2])
    near = lambda c: (colour - c).norm(dim=-1) < 0.1  # noqa: E731
    assert int(near(blue).sum()) > 0 and int(near(green).sum()) > 0
    assert int((near(blue) | near(green)).sum()) > 0.9 * len(colour)  # no red (their clothing), no yellow (own hair)
    rows = torch.nonzero(seen)[:, 0]  # image rows: the hair lies above the clothing
    assert float(rows[near(green)].float().mean()) < float(rows[near(blue)].float().mean())
    one = load(tiny_trained["loose"])
    with pytest.raises(DeltaError, match="one NeRF"):
        put_on(load(tiny_trained["tight"]).model, one.model, ["hair"])


def test_a_layer_on_an_avatar_of_one_nerf_is_worn_alone(tiny_trained):
    body, wearer = load(tiny_trained["tight"]), load(tiny_trained["loose"])
    layered(wearer.model, (0.9, 0.1, 0.1), (0.1, 0.8, 0.2))
    put_on(body.model, wearer.model, ["hair"])
    assert body.model.nerf.names == ("hair",) and body.model.nerf.layers["hair"] is wearer.model.nerf.layers["hair"]
    with pytest.raises(DeltaError, match=r"has the layers \['hair'\], not \['clothing'\]"):
        check_wearable(load(tiny_trained["tight"]).model, body.model, ["clothing"])


class HiddenHair(Part):
    """Hair above the neck, and a hair band within ``SHELL`` / 2 of the body below it: inside the clothing
    shell, which hides it from every camera (hair grown inside a skirt). Its top, up to ``NEAR`` below the
    neck, lies within the seen hair's grown margin."""

    def forward(self, x):
        colour, above = super().forward(x)
        d, _ = self.tree.query(x.detach().cpu().numpy(), k=1)
        band = torch.from_numpy(d < SHELL / 2).to(x) * (x[:, 1] <= self.neck).to(x) * 4000.0
        return colour, above + band


#: the top of the hidden band (m below the neck) that a margin grown around the seen hair would hold
NEAR = (0.03, 0.06)


def test_a_layer_worn_alone_leaves_behind_what_its_capture_never_showed(tiny_trained):
    """The wearer's hair layer also fills a band inside its clothing, below the neck, that no training frame
    sees. Confined to where its own frames see it, the hair rendered alone keeps every pixel where the
    avatar shows its hair and has nothing left in the band: on the body below the neck, right under the
    seen hair too (hair is not worn under clothing: the capture's masks rule it out behind the clothing's
    surface), and in the images."""
    from delta.fields.networks import LayeredNeRF

    wearer = load(tiny_trained["tight"])
    neck = layered(wearer.model, (0.9, 0.1, 0.1), (0.1, 0.8, 0.2))
    m = wearer.model
    cano = (m.canonical_T[..., :3] @ m.body.v_template[..., None]).squeeze(-1) + m.canonical_T[..., 3]
    m.nerf.layers["hair"] = HiddenHair(cano, (0.1, 0.8, 0.2), neck, True)
    whole, hair = m.nerf, m.nerf.layers["hair"]
    torso = cano[(cano[:, 1] < neck - 0.15) & (cano[:, 1] > neck - 0.5)]  # on the body: in the hidden band
    assert float(hair(torso)[1].min()) == 4000.0
    frames = [int(f) for f in wearer.data.train]

    def hair_alone(frame):
        m.nerf = LayeredNeRF.of({"hair": whole.layers["hair"]})
        try:
            return render_image(m, frame, soft_silhouette=False)["nerf_mask"]
        finally:
            m.nerf = whole

    near = cano[(cano[:, 1] < neck - NEAR[0]) & (cano[:, 1] > neck - NEAR[1])]
    with torch.no_grad():
        renders = {f: render_image(m, f, soft_silhouette=False) for f in frames}
        shown = {f: r["layer_hair"] > 0.5 for f, r in renders.items()}
        # the capture's parsing: the exterior and the hair where the avatar shows them
        exterior, hair_mask = torch.zeros(wearer.data.exterior.shape), torch.zeros(wearer.data.exterior.shape)
        for f in frames:
            exterior[f], hair_mask[f] = (renders[f]["nerf_mask"] > 0.5).float(), shown[f].float()
        wearer.data.exterior, wearer.data.hair = exterior, hair_mask
        before = {f: hair_alone(f) > 0.5 for f in frames}
        confine(wearer, ["hair"])
        after = {f: hair_alone(f) > 0.5 for f in frames}
    assert whole.layers["hair"] is not hair and float(whole.layers["hair"](torso)[1].max()) == 0.0
    assert float(hair(near)[1].min()) == 4000.0 and float(whole.layers["hair"](near)[1].max()) == 0.0
    for f in frames:
        assert int(shown[f].sum()) > 0 and int((shown[f] & ~after[f]).sum()) <= 0.1 * int(shown[f].sum())  # kept
        assert int(before[f].sum()) > 3 * int(shown[f].sum())  # alone, the band came out ...
        assert int((after[f] & ~shown[f]).sum()) <= 0.1 * int(shown[f].sum())  # ... and now hardly any


def test_the_worn_surface_is_the_given_layers_and_the_kept_ones(tmp_path):
    """Scored garments of a layer worn alone: the wearer's mesh of that layer and the body's own of the layer it
    keeps, not the wearer's whole exterior; a layer without a mesh adds nothing."""
    from delta.applications.dress import worn_surface
    from delta.export.meshes import MeshPart, read_mesh, write_mesh

    def tri(x, n=1):
        v = np.array([[x, 0, 0], [x + 1, 0, 0], [x, 1, 0]] * n, float)
        return MeshPart(v, np.arange(3 * n).reshape(-1, 3), np.full((3 * n, 3), 0.5))

    (tmp_path / "body").mkdir()
    (tmp_path / "wearer").mkdir()
    write_mesh(tmp_path / "body" / "clothing_nerf_space.ply", tri(9.0, 6))  # the whole exteriors
    write_mesh(tmp_path / "wearer" / "clothing_nerf_space.ply", tri(9.0, 9))
    write_mesh(tmp_path / "body" / "layer_clothing_nerf_space.ply", tri(0.0, 5))
    write_mesh(tmp_path / "body" / "layer_hair_nerf_space.ply", tri(1.0))
    write_mesh(tmp_path / "wearer" / "layer_clothing_nerf_space.ply", tri(2.0, 7))
    write_mesh(tmp_path / "wearer" / "layer_hair_nerf_space.ply", tri(3.0, 2))
    body, wearer = tmp_path / "body" / "clothing_nerf_space.ply", tmp_path / "wearer" / "clothing_nerf_space.ply"
    assert worn_surface(body, wearer, [], [], tmp_path / "w.ply") == wearer  # the whole exterior
    out = worn_surface(body, wearer, ["hair"], ["clothing"], tmp_path / "w.ply")
    mesh = read_mesh(out)
    assert len(mesh.faces) == 2 + 5 and set(np.round(mesh.vertices[:, 0]).astype(int)) == {0, 1, 3, 4}  # no 9s
    assert int(mesh.faces.max()) == len(mesh.vertices) - 1
    (tmp_path / "body" / "layer_clothing_nerf_space.ply").unlink()  # an empty layer: no mesh
    assert len(read_mesh(worn_surface(body, wearer, ["hair"], ["clothing"], tmp_path / "v.ply")).faces) == 2
