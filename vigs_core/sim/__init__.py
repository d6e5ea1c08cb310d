"""Visual-inertial simulator: scenes, ray-cast rendering with exact depth, IMU synthesis, hybrid
sequences from real IMU + real ground-truth motion, degradations, EuRoC ASL / ROS 2 bag writers.

* :mod:`vigs_core.sim.scene` -- :class:`Scene` (oriented boxes, slab-test ray casting),
  :func:`build_room_scene` (a room around a trajectory with objects off the path).
* :mod:`vigs_core.sim.texture` -- :class:`SurfaceTextures`: procedural, analytically prefiltered textures
  (optionally photographs, mip-mapped).
* :mod:`vigs_core.sim.render` -- :class:`Renderer` through a :class:`~vigs_core.camera.CameraModel`
  (distortion included): images and pixel-centre depth.
* :mod:`vigs_core.sim.trajectory` -- procedural, spline and sampled body motions.
* :mod:`vigs_core.sim.imu_synthesis` -- :func:`synthesize_imu` (``a = R^T (p'' - g)``, ``omega`` from ``R'``,
  white noise and bias random walks).
* :mod:`vigs_core.sim.degrade` -- motion blur, exposure changes, over-exposure, low light with shot and
  read noise, frame stride and drops.
* :mod:`vigs_core.sim.hybrid` -- :class:`SimSequence`, :func:`hybrid_source`, :func:`synthetic_source`.
* :mod:`vigs_core.sim.writers` -- :class:`AslWriter` (EuRoC ASL folder with depth); bags are written by
  :class:`vigs_core.io.rosbag.BagWriter`.

The command line front end is ``vigs sim`` (:mod:`vigs_cli.sim_cmd`).
"""
