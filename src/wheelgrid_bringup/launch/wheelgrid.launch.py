"""ros2 launch wheelgrid_bringup wheelgrid.launch.py [params:=FILE] [bag:=BAG] [rate:=R]
[iphone:=true] [drive:=false] [motor_port:=/dev/ttyUSB0]

For machines with a full ROS 2 Jazzy install: the same nodes and the same parameter file as
`wheelgrid launch` (which needs neither launch nor ros2). A bag is replayed with `ros2 bag play`.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.conditions import IfCondition, LaunchConfigurationEquals, LaunchConfigurationNotEquals
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

# (package, executable, node name) -- keep in step with wheelgrid_bringup.supervisor.NODES.
CHAIN = [
    ("wheelgrid_nav", "grid", "grid"),
    ("wheelgrid_nav", "planner", "planner"),
]
# A replay maps every frame, as `wheelgrid launch --bag` and `wheelgrid map` do; live, the
# mapper keeps only the newest frame (max_queue 1 in the parameter file).
REPLAY_MAPPER = {"max_queue": 1000}


def generate_launch_description():
    default_params = os.path.join(
        get_package_share_directory("wheelgrid_bringup"), "wheelgrid.yaml"
    )
    params = LaunchConfiguration("params")
    actions = [
        DeclareLaunchArgument("params", default_value=default_params),
        DeclareLaunchArgument("bag", default_value=""),
        DeclareLaunchArgument("rate", default_value="1.0"),
        DeclareLaunchArgument("iphone", default_value="false"),
        DeclareLaunchArgument("drive", default_value="true"),
        DeclareLaunchArgument("motor_port", default_value="/dev/ttyUSB0"),
    ]
    for extra, condition in (
        ([], LaunchConfigurationEquals("bag", "")),
        ([REPLAY_MAPPER], LaunchConfigurationNotEquals("bag", "")),
    ):
        actions.append(
            Node(
                package="wheelgrid_mapping",
                executable="mapper",
                name="mapper",
                parameters=[params, *extra],
                output="screen",
                condition=condition,
            )
        )
    for package, executable, name in CHAIN:
        actions.append(
            Node(
                package=package,
                executable=executable,
                name=name,
                parameters=[params],
                output="screen",
            )
        )
    actions.append(
        Node(
            package="wheelgrid_drive",
            executable="drive",
            name="drive",
            parameters=[params, {"port": LaunchConfiguration("motor_port")}],
            output="screen",
            condition=IfCondition(LaunchConfiguration("drive")),
        )
    )
    actions.append(
        Node(
            package="wheelgrid_mapping",
            executable="iphone_bridge",
            name="iphone_bridge",
            parameters=[params],
            output="screen",
            condition=IfCondition(LaunchConfiguration("iphone")),
        )
    )
    actions.append(
        ExecuteProcess(
            cmd=[
                "ros2",
                "bag",
                "play",
                LaunchConfiguration("bag"),
                "--rate",
                LaunchConfiguration("rate"),
            ],
            output="screen",
            condition=LaunchConfigurationNotEquals("bag", ""),
        )
    )
    return LaunchDescription(actions)
