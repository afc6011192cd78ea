"""Parts of the body by its skeleton: the heights between which long hair passes from the trunk to the head."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from delta.body.parts import hair_span
from tests.conftest import tree_model


def named(joint_names: list[str]):
    """The 4-joint tree fixture with other joint names (joints at y = 0, 0, 0 and 1)."""
    return dataclasses.replace(tree_model(), joint_names=joint_names)


def test_the_span_runs_from_the_shoulders_mean_height_to_the_heads():
    body = named(["root", "upperarm01.L", "upperarm01.R", "head"])
    joints = torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.3, 0.0], [-0.2, 0.5, 0.0], [0.0, 0.9, 0.1]], dtype=torch.float64)
    assert hair_span(body, joints) == pytest.approx((0.4, 0.9))
    # SMPL-X's names
    body = named(["pelvis", "left_shoulder", "right_shoulder", "head"])
    assert hair_span(body, joints) == pytest.approx((0.4, 0.9))


def test_no_span_without_a_head_or_shoulders_or_with_the_head_below_them():
    joints = torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.3, 0.0], [-0.2, 0.5, 0.0], [0.0, 0.9, 0.1]], dtype=torch.float64)
    assert hair_span(named(["root", "upperarm01.L", "upperarm01.R", "neck"]), joints) is None
    assert hair_span(named(["root", "a", "b", "head"]), joints) is None
    low_head = joints.clone()
    low_head[3, 1] = 0.2
    assert hair_span(named(["root", "upperarm01.L", "upperarm01.R", "head"]), low_head) is None
