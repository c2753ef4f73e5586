"""Scan sources: CARMEN logs, MCAP (ROS 2), the built-in simulator."""
