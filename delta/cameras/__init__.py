"""Camera models: scaled orthographic (the paper's) and pinhole with lens distortion."""

from delta.cameras.models import OrthographicCamera, PinholeCamera, distort, undistort

__all__ = ["OrthographicCamera", "PinholeCamera", "distort", "undistort"]
