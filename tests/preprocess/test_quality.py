"""Frame quality: which edges a person runs off, and which frames motion blurred."""

import cv2
import numpy as np
import pytest

from delta.data.quality import CUT_BAND, CUT_CONTACT, blurred, cut_edges, sharpness


@pytest.mark.parametrize("width", [1, 3, 5, 10, 40])
def test_a_person_runs_off_the_bottom_edge_where_the_contact_there_is_long_enough(width):
    # a 300-pixel person whose foot of ``width`` pixels reaches the last row: a sliver of contact (a heel's
    # tip) cuts off nothing, a foot across the edge does
    mask = np.zeros((400, 400), np.uint8)
    mask[99:380, 150:250] = 255
    mask[380:, 200 : 200 + width] = 255
    assert cut_edges(mask) == (("bottom",) if width >= CUT_CONTACT * 301 else ())
    assert cut_edges(mask, contact=0.0) == ("bottom",)  # any contact at all
    assert (cut_edges(mask) == ()) == (width < 5)


@pytest.mark.parametrize("fade", [0, 1, 2, 3, 5, 7, 8, 12])
def test_an_arm_across_the_edge_counts_where_the_matte_fades_out_over_the_last_pixels(fade):
    # a 1080 x 720 frame, an arm 40 pixels thick crossing the right edge; its matte, brought up from a model's
    # resolution, fades out over the last ``fade`` columns: 255 (k + 0.5) / fade on the k-th from the border,
    # so the first column over half-way is the (fade // 2)-th. The band looked in is 4 px at 1080: the arm
    # runs off the image for a fade up to 7 px; on the outermost column alone, only without one (0 or 1 px)
    mask = np.zeros((1080, 720), np.uint8)
    mask[100:1000, 300:500] = 255  # the body: a box 900 pixels tall (contact needs 14 rows)
    mask[300:340, 500:] = 255
    for k in range(fade):
        mask[300:340, 719 - k] = round(255 * (k + 0.5) / fade)
    assert round(CUT_BAND * 1080) == 4
    assert cut_edges(mask) == (("right",) if fade <= 7 else ())
    assert cut_edges(mask, band=0.0) == (("right",) if fade <= 1 else ())


def test_the_edges_a_person_crosses_are_named_in_order_and_nothing_for_an_empty_mask():
    mask = np.zeros((100, 80), np.uint8)
    assert cut_edges(mask) == ()
    mask[30:100, 0:50] = 255  # off the left and the bottom
    assert cut_edges(mask) == ("left", "bottom")
    mask[0:40, 60:80] = 255  # and the top and the right
    assert cut_edges(mask) == ("left", "top", "right", "bottom")


def test_a_motion_blurred_frame_is_found_among_sharp_ones():
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 255, (256, 256, 3)).astype(np.uint8), (0, 0), 1.0)
    mask = np.zeros((256, 256), np.uint8)
    mask[40:216, 60:196] = 255
    kernel = np.zeros((15, 15), np.float32)
    kernel[7, :] = 1 / 15  # a horizontal smear
    smeared = cv2.filter2D(texture, -1, kernel)
    scores = {i: sharpness(texture, mask) for i in range(4)}
    scores[4] = sharpness(smeared, mask)
    assert scores[4] < 0.3 * scores[0]
    assert blurred(scores) == [4]
