"""ROS 2 binding of DeepSync.

Thin rclpy nodes around the ROS-agnostic ``deepsync`` core stages, plus launch files and the
single module that converts between rclpy messages and core types. Nothing in this package's
``__init__`` imports rclpy, so the package can be imported (and its pure parts tested) without ROS.
"""
