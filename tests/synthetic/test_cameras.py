"""Camera models: projection against OpenCV, ray round trips, distortion inverse."""

import cv2
import numpy as np
import pytest
import torch

from delta.cameras.models import OrthographicCamera, PinholeCamera, distort, look_at, metres_per_pixel, undistort


def pinhole(dist=(0.0, 0.0, 0.0, 0.0, 0.0)):
    K = torch.tensor([[600.0, 0, 250], [0, 610, 260], [0, 0, 1]], dtype=torch.float64)
    R, t = look_at(torch.tensor([0.5, 0.3, 3.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                   torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))  # fmt: skip
    return PinholeCamera(K, R, t, torch.tensor(dist, dtype=torch.float64), 512, 512)


def points(n=200, seed=0):
    return torch.from_numpy(np.random.default_rng(seed).uniform(-0.8, 0.8, size=(n, 3)))


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), (-0.2, 0.05, 0.001, -0.002, 0.01)])
def test_pinhole_matches_opencv(dist):
    cam = pinhole(dist)
    X = points()
    uv, depth = cam.project(X)
    rvec = cv2.Rodrigues(cam.R.numpy())[0]
    ref, _ = cv2.projectPoints(X.numpy(), rvec, cam.t.numpy(), cam.K.numpy(), np.asarray(dist, dtype=np.float64))
    np.testing.assert_allclose(uv.numpy(), ref[:, 0], atol=1e-8)
    np.testing.assert_allclose(depth.numpy(), (X @ cam.R.T + cam.t)[:, 2].numpy())


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), (-0.2, 0.05, 0.001, -0.002, 0.01)])
def test_pinhole_ray_round_trip(dist):
    cam = pinhole(dist)
    X = points()
    uv, _ = cam.project(X)
    o, d = cam.rays(uv)
    along = ((X - o) * d).sum(-1, keepdim=True)
    assert ((o + along * d) - X).norm(dim=-1).max() < 1e-7
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(len(X), dtype=torch.float64))


def test_look_at_axes():
    cam = pinhole()
    uv, z = cam.project(torch.zeros(1, 3, dtype=torch.float64))
    np.testing.assert_allclose(uv.numpy()[0], [250, 260], atol=1e-9)  # the target lands on the principal point
    up, _ = cam.project(torch.tensor([[0.0, 0.2, 0.0]], dtype=torch.float64))
    assert up[0, 1] < 260  # world up is image up


def test_undistort_inverts_distort():
    k = torch.tensor([-0.25, 0.08, 0.002, -0.001, 0.0], dtype=torch.float64)
    xy = torch.from_numpy(np.random.default_rng(1).uniform(-0.5, 0.5, size=(500, 2)))
    torch.testing.assert_close(undistort(distort(xy, k), k), xy, atol=1e-10, rtol=0)
    # (distort itself is checked against cv2.projectPoints above)


def test_orthographic_round_trip_and_convention():
    cam = OrthographicCamera(torch.tensor(1.1, dtype=torch.float64), torch.tensor([0.05, -0.1], dtype=torch.float64),
                             200, 100)  # fmt: skip
    X = points()
    uv, depth = cam.project(X)
    o, d = cam.rays(uv)
    torch.testing.assert_close(o[:, :2], X[:, :2])
    torch.testing.assert_close(depth, -X[:, 2])
    assert (d[:, 2] == -1).all()
    # s (X + t_x) = -1 is the left image border, s (Y + t_y) = 1 the top border
    corner = torch.tensor([[-1 / 1.1 - 0.05, 1 / 1.1 + 0.1, 0.0]], dtype=torch.float64)
    np.testing.assert_allclose(cam.project(corner)[0].numpy(), [[0.0, 0.0]], atol=1e-12)


def test_camera_gradients():
    cam = pinhole((-0.2, 0.05, 0.0, 0.0, 0.0))
    X = points(5).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: cam.project(x)[0], (X,))
    s = torch.tensor(0.9, dtype=torch.float64, requires_grad=True)
    t = torch.tensor([0.1, 0.2], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda s_, t_: OrthographicCamera(s_, t_, 64, 64).project(X.detach())[0], (s, t))


@pytest.mark.parametrize("pitch,roll", [(0.0, 0.0), (20.0, 15.0), (-12.0, -30.0)])
def test_a_generated_camera_looks_down_by_its_pitch_and_is_rolled_by_its_roll(pitch, roll):
    from delta.synthetic.generate import make_camera
    from delta.synthetic.spec import parse_subject

    spec = parse_subject("s", {"camera_pitch": pitch, "camera_roll": roll, "resolution": 256})
    cam = make_camera(spec, 2.0, 1.0)
    optical = cam.R[2]  # the optical axis in the world
    assert np.degrees(np.arcsin(-float(optical[1]))) == pytest.approx(pitch, abs=1e-9)  # below the horizon
    target = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.3, 0.0]], dtype=torch.float64)  # a vertical through it
    uv, _ = cam.project(target)
    np.testing.assert_allclose(uv[0].numpy(), [128.0, 128.0], atol=1e-9)  # framed at the centre
    du, dv = (uv[1] - uv[0]).tolist()
    # the world's vertical appears turned clockwise by the roll (image v grows downwards)
    assert np.degrees(np.arctan2(-du, -dv)) == pytest.approx(-roll, abs=1e-6)


def test_metres_per_pixel_is_the_width_of_one_pixel_at_the_point():
    """A point moved by metres_per_pixel along the camera's own x axis moves one pixel along the row
    (pinhole: away from the image centre too, distortion off; orthographic: anywhere)."""
    D = torch.float64
    R, t = look_at(torch.tensor([0.3, 1.2, 3.5], dtype=D), torch.tensor([0.0, 0.9, 0.0], dtype=D),
                   torch.tensor([0.0, 1.0, 0.0], dtype=D))  # fmt: skip
    K = torch.tensor([[610.0, 0.0, 250.0], [0.0, 640.0, 260.0], [0.0, 0.0, 1.0]], dtype=D)
    pin = PinholeCamera(K, R, t, torch.zeros(5, dtype=D), 512, 512)
    ortho = OrthographicCamera(torch.tensor(0.8, dtype=D), torch.tensor([0.1, -0.9], dtype=D), 512, 384)
    points = torch.tensor([[0.0, 0.9, 0.0], [0.4, 1.5, -0.3], [-0.5, 0.2, 0.6]], dtype=D)
    for cam, x_axis in ((pin, R[0]), (ortho, torch.tensor([1.0, 0.0, 0.0], dtype=D))):
        mpp = metres_per_pixel(cam, points)
        assert mpp.shape == (3,) and bool((mpp > 0).all())
        step = 1e-3  # of a pixel: the pinhole's change of depth along x is nil, its projection linear
        uv, _ = cam.project(points)
        uv2, _ = cam.project(points + step * mpp[:, None] * x_axis)
        torch.testing.assert_close((uv2 - uv)[:, 0] / step, torch.ones(3, dtype=D), rtol=0, atol=1e-6)
        torch.testing.assert_close((uv2 - uv)[:, 1] / step, torch.zeros(3, dtype=D), rtol=0, atol=1e-6)
    # twice as far from a pinhole, a pixel is twice as wide
    far = pin.center + 2 * (points - pin.center)
    torch.testing.assert_close(metres_per_pixel(pin, far), 2 * metres_per_pixel(pin, points))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_an_ideal_lens_projects_and_casts_as_a_zero_distortion_bit_for_bit(dtype):
    """An avatar's camera has no distortion (None: its frames were undistorted) and skips the 20-step
    inverse; a zero distortion inverts exactly, so nothing the avatar renders changes."""
    zero = pinhole()
    ideal = PinholeCamera(zero.K, zero.R, zero.t, None, 512, 512)
    X = points().to(dtype)
    for a, b in zip(ideal.project(X), zero.project(X)):
        assert torch.equal(a, b)
    uv = torch.rand(300, 2, generator=torch.Generator().manual_seed(0), dtype=dtype) * 512
    for a, b in zip(ideal.rays(uv), zero.rays(uv)):
        assert torch.equal(a, b)
    assert not torch.equal(pinhole((-0.2, 0, 0, 0, 0)).rays(uv)[1], zero.rays(uv)[1])
