"""Thin rclpy nodes, the launcher and bag replay around vigs_core."""
