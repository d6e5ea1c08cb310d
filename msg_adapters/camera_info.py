"""``sensor_msgs/CameraInfo`` <-> :class:`vigs_core.camera.CameraModel`.

Distortion models (``distortion_model`` and ``d``):

* ``plumb_bob``: ``d = (k1, k2, p1, p2, k3)`` -> CameraModel ``"radtan"`` (all zero -> ``"none"``);
* ``equidistant``: ``d = (k1, k2, k3, k4)`` (Kannala-Brandt, as in camera_calibration) -> ``"equidistant"``;
* ``""`` or any model with an empty ``d`` -> ``"none"``.

Intrinsics come from ``k`` (3x3 row-major): ``fx = k[0], cx = k[2], fy = k[4], cy = k[5]``. Binning > 1 and a
partial ROI change the effective intrinsics; they are rejected rather than silently misread.
"""
from __future__ import annotations

import numpy as np

from msg_adapters.common import field, finite_array, make_header, numeric
from msg_adapters.types import MessageTypes
from vigs_core.camera import CameraModel

_EXPECTED = "'plumb_bob' with 5 coefficients, 'equidistant' with 4, or an empty d"


def camera_info_to_model(msg) -> CameraModel:
    """CameraModel of a CameraInfo message.

    Raises:
        ValueError: unknown distortion model, wrong coefficient count, non-positive focal length or
            image size, binning > 1 or a partial ROI.
    """
    width = int(field(msg, "width", "CameraInfo"))
    height = int(field(msg, "height", "CameraInfo"))
    if width <= 0 or height <= 0:
        raise ValueError(f"CameraInfo: image size {width}x{height}; expected width and height > 0")
    k = finite_array(numeric(field(msg, "k", "CameraInfo"), np.float64, "CameraInfo.k"), (9,), "CameraInfo.k")
    if k[0] <= 0 or k[4] <= 0:
        raise ValueError(f"CameraInfo: focal lengths fx={k[0]}, fy={k[4]} in k; expected both > 0 (is k all zero?)")
    binning = (int(field(msg, "binning_x", "CameraInfo")), int(field(msg, "binning_y", "CameraInfo")))
    if max(binning) > 1:
        raise ValueError(f"CameraInfo: binning {binning} is not supported; expected 0 or 1")
    roi = field(msg, "roi", "CameraInfo")
    roi_wh = (int(roi.width), int(roi.height))
    if roi_wh != (0, 0) and roi_wh != (width, height):
        raise ValueError(f"CameraInfo: partial ROI {roi_wh} of a {width}x{height} image is not supported")
    model = str(field(msg, "distortion_model", "CameraInfo"))
    d = numeric(field(msg, "d", "CameraInfo"), np.float64, "CameraInfo.d")
    if d.size == 0 or (model == "plumb_bob" and d.size == 5 and not np.any(d)):
        distortion, coeffs = "none", ()
    elif model == "plumb_bob" and d.size == 5:
        distortion, coeffs = "radtan", tuple(d)
    elif model == "equidistant" and d.size == 4:
        distortion, coeffs = "equidistant", tuple(d)
    else:
        raise ValueError(f"CameraInfo: distortion_model {model!r} with {d.size} coefficients; expected {_EXPECTED}")
    return CameraModel(width, height, k[0], k[4], k[2], k[5], distortion, coeffs)


def model_to_camera_info(types: MessageTypes, camera: CameraModel, t_ns: int, frame_id: str):
    """CameraInfo of a CameraModel (``p`` = ``[K | 0]``, ``r`` = identity: a monocular camera)."""
    if camera.distortion == "radtan":
        model, d = "plumb_bob", list(camera.coeffs) + [0.0] * (5 - len(camera.coeffs))
    elif camera.distortion == "equidistant":
        model, d = "equidistant", list(camera.coeffs)
    else:
        model, d = "plumb_bob", [0.0] * 5
    K = camera.K().numpy()
    P = np.concatenate([K, np.zeros((3, 1))], axis=1)
    return types.new(
        "sensor_msgs/msg/CameraInfo",
        header=make_header(types, t_ns, frame_id),
        height=camera.height,
        width=camera.width,
        distortion_model=model,
        d=types.sequence(d, np.float64),
        k=K.reshape(-1),
        r=np.eye(3).reshape(-1),
        p=P.reshape(-1),
        binning_x=0,
        binning_y=0,
        roi=types.new("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                      do_rectify=False),
    )
