"""Conversions between ROS 2 messages (rclpy or rosbags classes) and vigs_core types. No node logic."""
