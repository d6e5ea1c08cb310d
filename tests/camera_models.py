"""Real and synthetic camera calibrations shared by the camera tests."""
from vigs_core.camera import CameraModel

EUROC_CAM0 = CameraModel(
    752, 480, 458.654, 457.296, 367.215, 248.375, "radtan", (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
)
# A radtan camera with k3 (the 5-coefficient OpenCV variant) and noticeable tangential terms.
RADTAN5 = CameraModel(640, 480, 520.0, 515.0, 322.5, 236.0, "radtan", (-0.25, 0.12, 0.001, -0.0015, -0.03))
# TUM-VI cam0 (Kalibr pinhole-equi), a 195-degree fisheye, 512x512.
TUMVI_CAM0 = CameraModel(
    512,
    512,
    190.97847715128717,
    190.9733070521226,
    254.93170605935475,
    256.8974428996504,
    "equidistant",
    (0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202, 0.00020293673591811182),
)
# A strongly distorting equidistant model (coefficients in the range Kalibr fits to GoPro-like lenses).
EQUI_STRONG = CameraModel(800, 600, 300.0, 301.0, 401.0, 298.5, "equidistant", (-0.05, 0.02, -0.008, 0.001))
