"""vigs_core: the pure library of VIGS-ROS (no ROS imports).

Geometry, cameras, IMU, frontend, solver, mapping, loop closure, simulation, evaluation and I/O.
Everything the system computes lives here and runs in one process without DDS.
"""
__version__ = "0.1.0"
