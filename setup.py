"""VIGS-ROS: pip-installable, and buildable by colcon as an ament_python package."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "vigs_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    description="Visual-inertial Gaussian-splatting SLAM for ROS 2 (monocular camera + IMU)",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(include=["vigs_core*", "msg_adapters*", "vigs_ros*", "vigs_cli*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/params", glob("params/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.xml")),
        # colcon: the nodes' executables where `ros2 run vigs_ros <exec>` looks (pip puts console scripts in bin)
        (f"lib/{PACKAGE}", sorted(glob("ros_executables/*"))),
    ],
    install_requires=["numpy", "scipy", "pyyaml", "opencv-python-headless", "torch", "numba"],
    zip_safe=True,
    entry_points={
        "console_scripts": [
            "vigs = vigs_cli.main:main",
            "vigs_imu_preintegration = vigs_ros.imu_preintegration_node:main",
            "vigs_frontend = vigs_ros.frontend_node:main",
            "vigs_mapper = vigs_ros.mapper_node:main",
            "vigs_loop_detector = vigs_ros.loop_detector_node:main",
            "vigs_viewer = vigs_ros.viewer_node:main",
        ],
    },
)
