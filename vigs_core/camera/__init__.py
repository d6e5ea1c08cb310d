"""Camera models: pinhole projection with radial-tangential or equidistant (fisheye) distortion,
iterative undistortion, intrinsics at pyramid levels and image undistortion to a pinhole camera.

* :class:`CameraModel` -- frozen dataclass; ``project``, ``unproject``, ``K``, ``scaled``,
  ``pyramid``, ``pinhole``, ``pixel_grid``, ``to_opencv`` (see :mod:`vigs_core.camera.model`).
* :class:`Undistorter` -- OpenCV remap maps from one camera to another (default: the pinhole camera
  that sees only valid pixels, :func:`inner_pinhole`).
* :mod:`vigs_core.camera.distortion` -- the distortion models on the normalized image plane.

Pixel centres are at integer coordinates (OpenCV/Kalibr convention).
"""
from vigs_core.camera.model import MIN_DEPTH, CameraModel
from vigs_core.camera.undistort import Undistorter, inner_pinhole

__all__ = ["CameraModel", "Undistorter", "inner_pinhole", "MIN_DEPTH"]
