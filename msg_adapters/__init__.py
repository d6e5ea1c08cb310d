"""Conversions between ROS 2 messages (rclpy or rosbags classes) and vigs_core types. No node logic.

Reading is duck-typed (rclpy and rosbags classes share field names); building takes a message-class
provider, :class:`~msg_adapters.types.RclpyTypes` or :class:`~msg_adapters.types.RosbagsTypes`.
Malformed messages raise ``ValueError`` saying what was wrong and what was expected.

Modules: ``types`` (providers), ``common`` (stamps, poses), ``image`` (Image, CompressedImage), ``imu``,
``camera_info`` (<-> CameraModel), ``odometry`` (Odometry, Path), ``tf`` (TransformStamped, TFMessage),
``vigs`` (Keyframe, NavState, PreintegratedImu, KeyframePoseUpdate, GaussianDelta).
"""
