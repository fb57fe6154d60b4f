"""DeepSync with robot_localization's dual EKF: a robot's odometry and IMU, plus DeepSync's fixes.

    ros2 launch deepsync_ros dual_ekf.launch.py odometry:=/diff_drive/odom imu:=/imu/data
    ros2 launch deepsync_ros dual_ekf.launch.py --show-args

Starts deepsync.launch.py (every argument of it passes through: source, towers, use_sim_time,
antenna_x, ...) with config/deepsync_ekf_poses.yaml on top of its parameters (independent fixes:
no tracker, back-to-back stacks, site biases counted as they repeat), and two ekf_node instances
configured by config/robot_localization_dual_ekf.yaml: ``ekf_filter_node_odom`` (odometry and IMU,
world frame odom, publishes odom -> base_link on odometry/local) and ``ekf_filter_node_map`` (the
same plus DeepSync's fixes, world frame map, publishes map -> odom on odometry/global), which
takes at most one fix every 5 s: topic_tools' throttle relays /deepsync/pose onto
/deepsync/pose_ekf at that rate.
Standard library and launch only, like deepsync.launch.py.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

PACKAGE = "deepsync_ros"
# the filters' input topics as the YAML names them, remapped onto the launch's arguments
ODOMETRY_INPUT = "odometry/wheel"
IMU_INPUT = "imu/data"
FILTERS = {"ekf_filter_node_odom": "odometry/local", "ekf_filter_node_map": "odometry/global"}
# DeepSync's fixes as the map filter takes them: at most one every 5 s (their multipath bias
# repeats from fix to fix over tens of metres; benchmarks/experiments/ekf_example_nees.py measures the rule)
POSE_TOPIC = "/deepsync/pose"
EKF_POSE_TOPIC = "/deepsync/pose_ekf"
EKF_POSES_PER_S = 0.2


def _share(*parts):
    return PathJoinSubstitution([FindPackageShare(PACKAGE), *parts])


def generate_launch_description():
    use_sim_time = LaunchConfiguration("use_sim_time")
    filters = [
        Node(package="robot_localization", executable="ekf_node", name=name, output="screen",
             parameters=[LaunchConfiguration("ekf_params_file"), {"use_sim_time": use_sim_time}],
             remappings=[(ODOMETRY_INPUT, LaunchConfiguration("odometry")), (IMU_INPUT, LaunchConfiguration("imu")),
                         ("odometry/filtered", output)])
        for name, output in FILTERS.items()
    ]
    return LaunchDescription([
        DeclareLaunchArgument("odometry", default_value="/odometry/wheel",
                              description="The robot's wheel odometry (nav_msgs/Odometry, twist in base_link)."),
        DeclareLaunchArgument("imu", default_value="/imu/data", description="The robot's IMU (sensor_msgs/Imu)."),
        DeclareLaunchArgument("ekf_params_file", default_value=_share("config", "robot_localization_dual_ekf.yaml"),
                              description="Both filters' parameters (keys /**/ekf_filter_node_odom and _map)."),
        DeclareLaunchArgument("use_sim_time", default_value="true",
                              description="As deepsync.launch.py's: the filters and the nodes on one clock."),
        IncludeLaunchDescription(
            PythonLaunchDescriptionSource(_share("launch", "deepsync.launch.py")),
            launch_arguments={"extra_params_file": _share("config", "deepsync_ekf_poses.yaml"),
                              "use_sim_time": use_sim_time}.items(),
        ),
        Node(package="topic_tools", executable="throttle", name="deepsync_pose_throttle", output="screen",
             parameters=[{"input_topic": POSE_TOPIC, "output_topic": EKF_POSE_TOPIC, "throttle_type": "messages",
                          "msgs_per_sec": EKF_POSES_PER_S, "use_sim_time": use_sim_time}]),
        *filters,
    ])
