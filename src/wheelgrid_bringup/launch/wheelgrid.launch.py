"""ros2 launch wheelgrid_bringup wheelgrid.launch.py [params:=FILE] [bag:=BAG] [rate:=R]
[clock:=true] [iphone:=true] [drive:=false] [motor_port:=/dev/ttyUSB0] [namespace:=NS]

For machines with a full ROS 2 Jazzy install: the same nodes and the same parameter file as
`wheelgrid launch` (which needs neither launch nor ros2). A rosbag2 bag is replayed with
`ros2 bag play`, a few seconds after the nodes start so that their subscriptions match first
(a frame sent before is lost, and a later one would set the map frame). ``motor_port`` given
overrides the parameter file's drive ``port``; left out, the file's port stands.
``iphone:=true`` and ``bag:=`` are refused together, as `wheelgrid launch` refuses them.
``clock:=true`` (with ``bag:=``, as `wheelgrid launch --bag --clock`) plays the bag with
``--clock`` and runs every node with ``use_sim_time``, on the bag's time.
``namespace:=NS`` runs the chain in NS, as `wheelgrid launch --namespace NS` does: the nodes
are pushed into it, the parameter file's plain node keys (``mapper:``) are applied to them
through a copy of the file (rcl matches a plain key to ``/mapper`` only), and a bag's topics
are replayed under it (``/clock`` stays global; ``/tf`` goes under it, as the mapper's
does). NS is absolute: an including launch file's own ``PushRosNamespace`` does not nest it.
A node that exits ends the launch, as `wheelgrid launch` stops the chain when any node dies:
a drive node went on driving its plan with its grid node or planner dead.
"""

import os
import tempfile
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import (
    DeclareLaunchArgument,
    ExecuteProcess,
    OpaqueFunction,
    SetLaunchConfiguration,
    Shutdown,
    TimerAction,
)
from launch.conditions import IfCondition
from launch.substitutions import (
    AndSubstitution,
    EqualsSubstitution,
    LaunchConfiguration,
    NotEqualsSubstitution,
)
from launch_ros.actions import Node, PushRosNamespace, SetParameter

# (package, executable, node name) -- keep in step with wheelgrid_bringup.supervisor.NODES.
CHAIN = [
    ("wheelgrid_nav", "grid", "grid"),
    ("wheelgrid_nav", "planner", "planner"),
]
# A replay maps every frame, as `wheelgrid launch --bag` and `wheelgrid map` do; live, the
# mapper keeps only the newest frame (max_queue 1 in the parameter file).
REPLAY_MAPPER = {"max_queue": 1000}
# seconds between the nodes' start and the replay's first message
REPLAY_DELAY_S = 5.0


def _check_arguments(context, *_args, **_kwargs):
    """Refuse what would start a chain other than the one asked for, before any node starts."""
    bag = context.launch_configurations.get("bag", "")
    iphone = context.launch_configurations.get("iphone", "false").lower() in ("true", "1")
    clock = context.launch_configurations.get("clock", "false").lower() in ("true", "1")
    if bag and iphone:
        raise RuntimeError("iphone:=true and bag:= are exclusive: one source of frames")
    if clock and not bag:
        raise RuntimeError("clock:=true needs bag:= (it sends the bag's time)")
    if bag.endswith(".bag"):
        raise RuntimeError(
            f"bag:={bag} is a ROS 1 bag, which ros2 bag play cannot read: convert it first "
            f"(`rosbags-convert --src {bag} --dst NEW_FOLDER`); `wheelgrid map` reads it as it is"
        )
    return []


def _namespace(context, *_args, **_kwargs):
    """``namespace:=NS``: the nodes after it in NS, and the parameter file's plain node keys
    applied to them (the file is read and copied by `wheelgrid launch`'s own functions, so
    both launchers apply a file alike). A namespace rcl refuses stops the launch here, before
    any node starts; a node would have refused it only in its own log."""
    from wheelgrid_bringup.launcher import check_namespace, namespaced_params_file

    ns = check_namespace(context.launch_configurations.get("namespace", ""))
    if not ns:
        return []
    params = Path(context.launch_configurations["params"])
    copy = namespaced_params_file(params, ns, Path(tempfile.mkdtemp(prefix="wheelgrid_launch_")))
    return [SetLaunchConfiguration("params", str(copy)), PushRosNamespace(ns)]


def _play_command(conf):
    """The ``ros2 bag play`` argv for the launch configurations ``conf`` (``[]`` without a
    bag): at ``rate:=``, with ``--clock`` for ``clock:=true``, the bag's topics remapped into
    ``namespace:=`` as `wheelgrid launch --namespace` replays them (``ros2 bag play`` has no
    namespace option, and its ``__ns`` leaves a bag's absolute names where they are)."""
    bag = conf.get("bag", "")
    if not bag:
        return []
    from wheelgrid_bringup.replay import sensor_topics
    from wheelgrid_common.bagio import BagError

    try:
        # the sensor data only, as `wheelgrid launch --bag` replays it: played whole, a
        # chair's recording's /cmd_vel and goals reach the running chain
        topics = sensor_topics(bag)
    except BagError as exc:
        raise RuntimeError(f"bag:={bag}: {exc}") from None
    if not topics:
        raise RuntimeError(f"bag:={bag} holds no sensor data to replay")
    cmd = ["ros2", "bag", "play", bag, "--rate", conf.get("rate", "1.0"), "--topics", *topics]
    if conf.get("clock", "false").lower() in ("true", "1"):
        cmd.append("--clock")
    if conf.get("namespace", "").strip("/"):
        from wheelgrid_bringup.launcher import check_namespace
        from wheelgrid_bringup.replay import play_remaps

        cmd += play_remaps(bag, check_namespace(conf["namespace"]))
    return cmd


def _replay(context, *_args, **_kwargs):
    """The bag's replay, a few seconds after the nodes start (their subscriptions match
    first). Read before the nodes start: a bag that cannot be opened starts none of them."""
    cmd = _play_command(context.launch_configurations)
    if not cmd:
        return []
    return [TimerAction(period=REPLAY_DELAY_S, actions=[ExecuteProcess(cmd=cmd, output="screen")])]


def generate_launch_description():
    default_params = os.path.join(
        get_package_share_directory("wheelgrid_bringup"), "wheelgrid.yaml"
    )
    params = LaunchConfiguration("params")
    actions = [
        DeclareLaunchArgument("params", default_value=default_params),
        DeclareLaunchArgument("bag", default_value=""),
        DeclareLaunchArgument("rate", default_value="1.0"),
        DeclareLaunchArgument("clock", default_value="false"),
        DeclareLaunchArgument("iphone", default_value="false"),
        DeclareLaunchArgument("drive", default_value="true"),
        DeclareLaunchArgument("motor_port", default_value=""),
        DeclareLaunchArgument("namespace", default_value=""),
        OpaqueFunction(function=_check_arguments),
        OpaqueFunction(function=_namespace),
        OpaqueFunction(function=_replay),
        # before the nodes: it reaches every node started after it
        SetParameter(
            name="use_sim_time", value=True, condition=IfCondition(LaunchConfiguration("clock"))
        ),
    ]
    bag = LaunchConfiguration("bag")
    no_bag, with_bag = EqualsSubstitution(bag, ""), NotEqualsSubstitution(bag, "")
    for extra, condition in (
        ([], IfCondition(no_bag)),
        ([REPLAY_MAPPER], IfCondition(with_bag)),
    ):
        actions.append(
            Node(
                package="wheelgrid_mapping",
                executable="mapper",
                name="mapper",
                parameters=[params, *extra],
                output="screen",
                condition=condition,
                on_exit=Shutdown(reason="mapper exited"),
                # time to save an unsaved map as it stops, as `wheelgrid launch` gives it
                # (supervisor.STOP_GRACE_S): at launch's 5 s a Ctrl-C during a loop closure
                # killed it before the save
                sigterm_timeout="25",
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
                on_exit=Shutdown(reason=f"{name} exited"),
            )
        )
    port = LaunchConfiguration("motor_port")
    for extra, given in (
        ([], EqualsSubstitution(port, "")),  # the parameter file's port
        ([{"port": port}], NotEqualsSubstitution(port, "")),
    ):
        actions.append(
            Node(
                package="wheelgrid_drive",
                executable="drive",
                name="drive",
                parameters=[params, *extra],
                output="screen",
                condition=IfCondition(AndSubstitution(LaunchConfiguration("drive"), given)),
                on_exit=Shutdown(reason="drive exited"),
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
            on_exit=Shutdown(reason="iphone_bridge exited"),
        )
    )
    return LaunchDescription(actions)
