"""launch_testing: the default launch publishes a pose on /deepsync/pose within 120 s.

Run by test/test_launch.py where ROS 2 is sourced and deepsync_ros is built (it is named so
that pytest does not collect it itself), or by hand:

    launch_test test/ros_launch/deepsync_pose_launch.py
"""

import os
import time
import unittest

import launch
import launch_testing
import launch_testing.actions
import launch_testing.asserts
import pytest
import rclpy
from ament_index_python.packages import get_package_share_directory
from geometry_msgs.msg import PoseWithCovarianceStamped
from launch.actions import IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource

POSE_TOPIC = "/deepsync/pose"
# Four nodes import numpy/scipy and build their templates before the first stack (1 s of signal);
# alone that takes seconds, but a full test run shares a loaded machine: the budget is generous,
# and the wait ends as soon as a pose comes.
WITHIN_S = 120.0


@pytest.mark.launch_test
def generate_test_description():
    launch_file = os.path.join(get_package_share_directory("deepsync_ros"), "launch", "deepsync.launch.py")
    return launch.LaunchDescription([
        IncludeLaunchDescription(PythonLaunchDescriptionSource(launch_file)),  # every default
        launch_testing.actions.ReadyToTest(),
    ])


class TestPose(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rclpy.init()
        cls.node = rclpy.create_node("deepsync_pose_probe")

    @classmethod
    def tearDownClass(cls):
        cls.node.destroy_node()
        rclpy.shutdown()

    def test_a_pose_within_the_budget(self):
        poses = []
        subscription = self.node.create_subscription(PoseWithCovarianceStamped, POSE_TOPIC, poses.append, 10)
        try:
            deadline = time.monotonic() + WITHIN_S
            while not poses and time.monotonic() < deadline:
                rclpy.spin_once(self.node, timeout_sec=0.5)
        finally:
            self.node.destroy_subscription(subscription)
        self.assertTrue(poses, f"no PoseWithCovarianceStamped on {POSE_TOPIC} within {WITHIN_S:.0f} s")
        pose = poses[0]
        self.assertEqual(pose.header.frame_id, "map")
        # x/y measured (finite, positive variance); orientation unmeasured (huge variance)
        self.assertGreater(pose.pose.covariance[0], 0.0)
        self.assertGreater(pose.pose.covariance[7], 0.0)
        self.assertGreaterEqual(pose.pose.covariance[35], 1e3)


@launch_testing.post_shutdown_test()
class TestShutdown(unittest.TestCase):
    def test_nodes_exit_cleanly(self, proc_info):
        # 0, or killed by the SIGINT / SIGTERM launch sends at shutdown; a crash (1) fails
        launch_testing.asserts.assertExitCodes(proc_info, allowable_exit_codes=[0, -2, -15])
