"""Bad subject specs fail with a clear message before anything is rendered."""

import pytest

from delta import DeltaError
from delta.synthetic.spec import parse_subject


def test_defaults():
    spec = parse_subject("s", {})
    assert spec.resolution == 512 and spec.num_frames == 130 and spec.camera == "pinhole"


@pytest.mark.parametrize(
    "raw,message",
    [
        ({"garments": ["cape"]}, r"subjects.s.garments\[0\]: unknown garment 'cape'"),
        ({"resolution": 0}, r"subjects.s.resolution: 0 is outside \[32, 4096\]"),
        ({"resolution": 100000}, r"resolution: 100000 is outside"),
        ({"resolution": 256.5}, r"resolution: expected an integer"),
        ({"turn_frames": 0, "novel_frames": 0}, r"turn_frames: 0 is outside|zero frames"),
        ({"garments": ["tshirt", "dress"]}, r"overlap"),
        ({"garments": [{"kind": "tshirt", "pattern": "paisley"}]}, r"unknown pattern 'paisley'"),
        ({"garments": [{"kind": "tshirt", "colors": [[2, 0, 0], [0, 0, 0]]}]}, r"colors\[0\].*\[0, 1\]"),
        ({"hair": "mohawk"}, r"hair: unknown value 'mohawk'"),
        ({"camera": "fisheye"}, r"camera: unknown value 'fisheye'"),
        ({"camera": "orthographic", "distortion": [0.1, 0, 0, 0, 0]}, r"orthographic camera has no lens"),
        ({"distortion": [0.1, 0]}, r"distortion: five numbers"),
        ({"phenotype": {"wingspan": 0.5}}, r"phenotype: a mapping over"),
        ({"phenotype": {"height": 1.5}}, r"phenotype: values must lie in \[0, 1\]"),
        ({"frames": 10}, r"unknown key\(s\) \['frames'\]"),
        ({"codec": "h265"}, r"codec: unknown value"),
        ({"framing": "feet"}, r"framing: unknown value 'feet'; known: \['full', 'upper', 'head'\]"),
        ({"camera_pitch": 75}, r"camera_pitch: expected a number in \[-60.0, 60.0\]"),
        ({"camera": "orthographic", "camera_roll": 10}, r"camera_pitch and camera_roll need the pinhole camera"),
    ],
)
def test_bad_specs_are_named(raw, message):
    with pytest.raises(DeltaError, match=message):
        parse_subject("s", raw)
