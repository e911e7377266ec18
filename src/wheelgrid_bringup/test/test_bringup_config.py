"""The bringup's one parameter file, the launch file and the command table stay in step with
the nodes: a misspelt parameter would otherwise be ignored silently by ROS."""

import ast
import dataclasses
import os
from pathlib import Path

import yaml

from wheelgrid_bringup.cli import COMMANDS, main
from wheelgrid_bringup.supervisor import (
    NODES,
    REPLAY_MAX_QUEUE,
    default_params_file,
    node_argv,
)

PKG = Path(__file__).resolve().parents[1]


def _declared() -> dict[str, set[str]]:
    from wheelgrid_drive.drive_node import DriveConfig
    from wheelgrid_mapping.iphone_bridge_node import BridgeConfig
    from wheelgrid_mapping.loop_closure import LoopClosureConfig
    from wheelgrid_mapping.mapper_node import MapperNodeConfig
    from wheelgrid_mapping.pipeline import MapperConfig
    from wheelgrid_mapping.preprocess import PreprocessConfig
    from wheelgrid_mapping.registration import RegistrationConfig
    from wheelgrid_nav.grid import GridNodeConfig
    from wheelgrid_nav.planner import PlannerConfig
    from wheelgrid_nav.planner_node import PlannerNodeConfig

    def names(cls, prefix=""):
        return {prefix + f.name for f in dataclasses.fields(cls)}

    return {
        "mapper": names(MapperNodeConfig)
        | names(PreprocessConfig, "preprocess.")
        | names(RegistrationConfig, "registration.")
        | names(MapperConfig, "mapper.")
        | names(LoopClosureConfig, "loop_closure."),
        "grid": names(GridNodeConfig),
        "planner": names(PlannerNodeConfig) | names(PlannerConfig),
        "drive": names(DriveConfig),
        "iphone_bridge": names(BridgeConfig),
    }


def _flatten(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _flatten(v, f"{prefix}{k}.")
        else:
            yield prefix + k


def test_every_parameter_in_the_yaml_is_declared_by_its_node():
    params = yaml.safe_load(default_params_file().read_text())
    declared = _declared()
    assert set(params) == set(declared)
    for node, section in params.items():
        keys = set(_flatten(section["ros__parameters"]))
        assert keys <= declared[node], f"{node}: undeclared {sorted(keys - declared[node])}"


def test_launch_file_starts_the_same_nodes_as_the_launcher():
    tree = ast.parse((PKG / "launch" / "wheelgrid.launch.py").read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Tuple) and len(node.elts) == 3:
            vals = [e.value for e in node.elts if isinstance(e, ast.Constant)]
            if len(vals) == 3 and vals[0].startswith("wheelgrid_"):
                names.add(vals[2])
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "Node":
            for kw in node.keywords:
                if kw.arg == "name" and isinstance(kw.value, ast.Constant):
                    names.add(kw.value.value)
    assert names == {"mapper", "grid", "planner", "drive", "iphone_bridge"}
    assert names <= set(NODES)
    # a bag replayed by ros2 launch maps every frame, as `wheelgrid launch --bag` does (the
    # mapper kept the parameter file's max_queue 1 there, and mapped another map)
    replay = next(
        ast.literal_eval(n.value)
        for n in ast.walk(tree)
        if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "REPLAY_MAPPER"
    )
    assert replay == {"max_queue": REPLAY_MAX_QUEUE}


def test_launch_file_refuses_two_sources_and_leaves_the_files_port_alone():
    """Read without `launch` (not installed here): iphone:=true with bag:= started both; a
    ROS 1 bag went to `ros2 bag play`, which cannot read it; motor_port's default
    /dev/ttyUSB0 overrode the parameter file's drive port; the replay started with the nodes,
    before their subscriptions matched; LaunchConfigurationEquals is deprecated on Jazzy."""
    import pytest

    text = (PKG / "launch" / "wheelgrid.launch.py").read_text()
    tree = ast.parse(text)
    assert "LaunchConfigurationEquals" not in text and "LaunchConfigurationNotEquals" not in text
    defaults = {
        n.args[0].value: getattr(n.keywords[0].value, "value", None)
        for n in ast.walk(tree)
        if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "DeclareLaunchArgument"
    }
    assert defaults["motor_port"] == ""
    timer = next(
        n
        for n in ast.walk(tree)
        if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "TimerAction"
    )
    assert "REPLAY_DELAY_S" in ast.unparse(timer) and "ExecuteProcess" in ast.unparse(timer)
    scope = _launch_functions(tree)

    def run(**conf):
        return scope["_check_arguments"](type("Ctx", (), {"launch_configurations": conf})())

    assert run(bag="/b", iphone="false") == [] and run(bag="", iphone="true") == []
    with pytest.raises(RuntimeError, match="exclusive"):
        run(bag="/b", iphone="true")
    with pytest.raises(RuntimeError, match="ROS 1 bag") as exc:
        run(bag="/x/scan.bag", iphone="false")
    # `wheelgrid launch --bag` refuses a ROS 1 bag too: the message sent users there (a review)
    assert "rosbags-convert --src /x/scan.bag" in str(exc.value)
    assert "wheelgrid launch" not in str(exc.value)
    # clock:=true mirrors `wheelgrid launch --bag --clock`: the bag's time on /clock, every
    # node on it; without a bag there is no time to send
    assert run(bag="/b", clock="true") == []
    with pytest.raises(RuntimeError, match="needs bag"):
        run(bag="", clock="true")
    assert defaults["clock"] == "false"
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)]
    plays = [ast.unparse(n) for n in calls if getattr(n.func, "id", "") == "TimerAction"]
    assert len(plays) == 1
    play = scope["_play_command"]
    assert play({}) == [] and play({"bag": ""}) == []
    # the sensor data only, as `wheelgrid launch --bag` replays it (commands stay out)
    scan = str(PKG.parents[1] / "bags" / "paper_room" / "scan")
    assert play({"bag": scan, "rate": "2.0"}) == [
        "ros2", "bag", "play", scan, "--rate", "2.0", "--topics", "/iphone/odometry",
        "/iphone/points",
    ]  # fmt: skip
    assert play({"bag": scan, "clock": "True"})[-1] == "--clock"
    with pytest.raises(RuntimeError, match="bag:=/b"):
        play({"bag": "/b"})
    # SetParameter reaches only the nodes started after it
    sim_time = [n for n in calls if getattr(n.func, "id", "") == "SetParameter"]
    nodes = [n for n in calls if getattr(n.func, "id", "") == "Node"]
    assert len(sim_time) == 1 and "use_sim_time" in ast.unparse(sim_time[0])
    assert all(sim_time[0].lineno < n.lineno for n in nodes)


def _launch_functions(tree: ast.Module, **names: object) -> dict:
    """The launch file's module-level constants and functions, run without `launch` (not on
    PyPI): the launch actions they return are stood in for by ``names``."""
    body = [
        n
        for n in tree.body
        if (isinstance(n, ast.FunctionDef) and n.name.startswith("_")) or isinstance(n, ast.Assign)
    ]
    scope: dict = {"Path": Path, "tempfile": __import__("tempfile"), **names}
    exec(compile(ast.Module(body, []), "launch", "exec"), scope)
    return scope


def test_launch_file_runs_the_chain_in_a_namespace(tmp_path, monkeypatch):
    """`wheelgrid launch --namespace` had no counterpart under ros2 launch: the nodes could be
    pushed into a namespace by an including file, but the parameter file's plain node keys
    then reached none of them (rcl matches ``mapper:`` to ``/mapper`` only), and ``ros2 bag
    play`` sent the bag's frames to ``/iphone/points``, where no namespaced node listens."""
    import pytest
    import yaml

    tree = ast.parse((PKG / "launch" / "wheelgrid.launch.py").read_text())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)]
    defaults = {
        n.args[0].value: getattr(n.keywords[0].value, "value", None)
        for n in calls
        if getattr(n.func, "id", "") == "DeclareLaunchArgument"
    }
    assert defaults["namespace"] == ""
    # the namespace is pushed, and the replay's bag read, before any node is declared
    opaque = {
        ast.unparse(n.keywords[0].value): n.lineno
        for n in calls
        if getattr(n.func, "id", "") == "OpaqueFunction"
    }
    first_node = min(n.lineno for n in calls if getattr(n.func, "id", "") == "Node")
    assert opaque.keys() == {"_check_arguments", "_namespace", "_replay"}
    assert max(opaque.values()) < first_node

    monkeypatch.setattr("tempfile.mkdtemp", lambda prefix="": str(tmp_path))
    scope = _launch_functions(
        tree,
        SetLaunchConfiguration=lambda name, value: ("set", name, value),
        PushRosNamespace=lambda ns: ("push", ns),
    )

    def namespace(ns: str) -> list:
        conf = {"namespace": ns, "params": str(default_params_file())}
        return scope["_namespace"](type("Ctx", (), {"launch_configurations": conf})())

    assert namespace("") == [] and namespace("/") == []
    (_, key, copy), push = namespace("chair1")
    assert key == "params" and push == ("push", "/chair1")
    nodes = yaml.safe_load(Path(copy).read_text())
    assert {"/chair1/mapper", "/chair1/grid", "/chair1/planner", "/chair1/drive"} <= set(nodes)
    with pytest.raises(ValueError, match="--namespace '9chair'"):
        namespace("9chair")

    bag = PKG.parents[1] / "bags" / "paper_room" / "scan"
    cmd = scope["_play_command"]({"bag": str(bag), "namespace": "/chair1", "clock": "true"})
    rules = cmd[cmd.index("--remap") + 1 :]
    assert "/iphone/points:=/chair1/iphone/points" in rules
    assert all(not r.startswith("/clock:") for r in rules)
    assert "--clock" in cmd[: cmd.index("--remap")]


def test_replayed_names_follow_the_namespace_but_the_clock_stays_global():
    from wheelgrid_bringup.replay import play_remaps, replayed_name

    assert replayed_name("/iphone/points", "/chair1") == "/chair1/iphone/points"
    assert replayed_name("/iphone/points", "") == "/iphone/points"
    assert replayed_name("/clock", "/a/b") == "/clock"
    # the transform tree is the chain's, as the mapper's relative `tf` is (two chairs crossed)
    assert replayed_name("/tf", "/a") == "/a/tf"
    bag = PKG.parents[1] / "bags" / "paper_room" / "scan"
    assert play_remaps(bag, "") == []


def test_launch_file_ends_the_launch_when_any_node_exits():
    """`wheelgrid launch` stops the chain when any node dies; under ros2 launch the others ran
    on, and the drive node went on driving its plan with its grid node or planner dead. The
    bag replay ending is no reason to stop."""
    tree = ast.parse((PKG / "launch" / "wheelgrid.launch.py").read_text())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)]
    nodes = [n for n in calls if getattr(n.func, "id", "") == "Node"]
    assert nodes
    for node in nodes:
        on_exit = next((kw.value for kw in node.keywords if kw.arg == "on_exit"), None)
        assert isinstance(on_exit, ast.Call) and getattr(on_exit.func, "id", "") == "Shutdown", (
            ast.unparse(node)
        )
    (play,) = [n for n in calls if getattr(n.func, "id", "") == "ExecuteProcess"]
    assert all(kw.arg != "on_exit" for kw in play.keywords)


def test_node_argv_passes_params_file_and_overrides():
    argv = node_argv("grid", Path("/p.yaml"), {"safe_height": 1.4, "thin_obstacle_guard": False})
    assert argv[argv.index("--params-file") + 1] == "/p.yaml"
    assert "safe_height:=1.4" in argv and "thin_obstacle_guard:=false" in argv
    assert "__node:=grid" in argv


def test_overrides_reach_a_node_as_the_strings_they_are():
    """``-p output_dir:=scan #2`` is YAML to rcl: the value became ``scan`` (the rest a
    comment), and the demo's maps went to a folder nobody named; a ``: `` in it made rcl
    refuse the argument."""
    import rclpy
    from rclpy.context import Context

    from wheelgrid_bringup.supervisor import override_text
    from wheelgrid_common.ros_env import configure_ros_env

    values = {"output_dir": "/tmp/scan #2", "port": "/dev/a: b", "quote": "it's", "n": 3}
    args = ["--ros-args"]
    for k, v in values.items():
        args += ["-p", f"{k}:={override_text(v)}"]
    configure_ros_env()
    ctx = Context()
    rclpy.init(args=args, context=ctx)
    try:
        node = rclpy.create_node("override_test", context=ctx)
        got = {k: p.value for k, p in node._parameter_overrides.items()}
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    assert got == values
    assert override_text(True) == "true" and override_text(0.5) == "0.5"


def test_an_empty_discovery_range_is_loopback_not_the_subnet():
    """Set but empty (`ROS_AUTOMATIC_DISCOVERY_RANGE= wheelgrid launch`, docker's ``-e``
    with the host's unset) is unset to ROS, which then discovers across the subnet: it was
    kept, and the chain multicast onto the LAN."""
    from wheelgrid_common.ros_env import configure_ros_env

    for value in ("", "  "):
        env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": value, "ROS_LOG_DIR": "/tmp/wg-env-test"}
        assert configure_ros_env(env)["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "ROS_LOG_DIR": "/tmp/wg-env-test"}
    assert configure_ros_env(env)["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"  # asked for


def test_help_lists_every_command_and_unknown_commands_exit_2(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out
    assert main(["no-such-command"]) == 2
    assert main([]) == 2


def test_launch_refuses_a_broken_params_file_before_any_node_starts(tmp_path, capsys):
    """rcl refuses a bad parameter file only inside each node (a traceback in its log, exit 1
    naming a dead node); the launch reads it first and names the file and the line."""
    import pytest

    from wheelgrid_bringup.launcher import check_params_file
    from wheelgrid_bringup.launcher import main as launch_main

    check_params_file(default_params_file())
    nested = tmp_path / "ns.yaml"
    nested.write_text("chair:\n  mapper:\n    ros__parameters: {topic: /x}\n")
    check_params_file(nested, "/chair")  # nodes under a namespace, as rcl reads them
    bad = tmp_path / "bad.yaml"
    for text, says in (
        ("mapper:\n  ros__parameters: {topic: [/x\n", "bad.yaml: not valid YAML at line 3"),
        ("preprocess: {voxel_size: 0.03}\n", "'preprocess/voxel_size' must hold a ros__param"),
        ("mapper:\n  ros__parameters: 5\n", "mapper's ros__parameters must be a mapping"),
        ("- mapper\n", "expected a mapping of node name"),
        # what only rcl's parser refuses: every node died on it after the start (a review)
        ("grid:\n  ros__parameters:\n    safe_height:\n", "rcl cannot read it: No value"),
        ("grid:\n  x: 1\n  ros__parameters: {safe_height: 1.6}\n", "Cannot have a value"),
        ("grid:\n  ros__parameters: {topics: [1, a]}\n", "Sequence should be of same type"),
    ):
        bad.write_text(text)
        with pytest.raises(ValueError) as info:
            check_params_file(bad)
        assert says in str(info.value), (text, str(info.value))
    assert launch_main(["--params", str(bad), "--no-drive", "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert "rcl cannot read it: Sequence should" in err and "Traceback" not in err


def test_a_section_that_reaches_no_node_of_the_chain_is_refused(tmp_path, capsys):
    """rcl ignores a section naming no node: `gird:` for `grid:` ran the grid on its
    defaults (a safe height of 1.5 m where the file said 1.7) with exit 0, and so did a file
    written for `chair2` under `--namespace chair1`. Wildcards and namespaced nodes reach."""
    import pytest

    from wheelgrid_bringup.launcher import check_params_file
    from wheelgrid_bringup.launcher import main as launch_main

    params = tmp_path / "p.yaml"
    for text, namespace in (
        ("gird:\n  ros__parameters: {safe_height: 1.7}\n", ""),
        ("chair2:\n  grid:\n    ros__parameters: {safe_height: 1.7}\n", "/chair1"),
        ("/chair2/grid:\n  ros__parameters: {safe_height: 1.7}\n", "/chair1"),
        ("chair1:\n  grid:\n    ros__parameters: {safe_height: 1.7}\n", ""),
        ("/*/grid:\n  ros__parameters: {safe_height: 1.7}\n", ""),  # * is one token
    ):
        params.write_text(text)
        with pytest.raises(ValueError, match="reaches no node of the chain"):
            check_params_file(params, namespace)
    params.write_text("gird:\n  ros__parameters: {safe_height: 1.7}\n")
    assert launch_main(["--params", str(params), "--no-drive", "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert "did you mean '/grid'?" in err and "Traceback" not in err
    for text, namespace in (
        ("grid:\n  ros__parameters: {safe_height: 1.7}\n", "/chair1"),
        ("chair1:\n  grid:\n    ros__parameters: {safe_height: 1.7}\n", "/chair1"),
        ("/**:\n  ros__parameters: {use_sim_time: true}\n", "/a/b"),
        ("/**/grid:\n  ros__parameters: {safe_height: 1.7}\n", ""),
        ("/*/grid:\n  ros__parameters: {safe_height: 1.7}\n", "/chair1"),
        ("/chair1/:\n  grid:\n    ros__parameters: {safe_height: 1.7}\n", "/chair1"),
    ):
        params.write_text(text)
        check_params_file(params, namespace)
    params.write_text("/gr*:\n  ros__parameters: {safe_height: 1.7}\n")  # rcl: no such key
    with pytest.raises(ValueError, match="only as whole name tokens"):
        check_params_file(params)


def test_the_namespaced_copy_is_the_params_file_as_checked(tmp_path):
    """`wheelgrid launch --namespace` read the params file twice, once to check it and once to
    copy it for the namespace: a file edited in between reached the nodes unchecked. The copy
    is now written from what the check read."""
    import yaml

    from wheelgrid_bringup.launcher import check_params_file, namespaced_params_file

    params = tmp_path / "p.yaml"
    params.write_text("mapper:\n  ros__parameters: {topic: /checked}\n")
    checked = check_params_file(params)
    params.write_text("mapper:\n  ros__parameters: 5\n")  # edited after the check
    copy = namespaced_params_file(params, "/chair1", tmp_path / "out", checked)
    assert yaml.safe_load(copy.read_text()) == {
        "/chair1/mapper": {"ros__parameters": {"topic": "/checked"}}
    }
    # a key with a '/' names its node already (rcl reads ``chair1/grid`` as /chair1/grid):
    # prefixed, it became /chair1/chair1/grid, and the grid ran on its defaults (a review)
    params.write_text("chair1/grid:\n  ros__parameters: {safe_height: 1.9}\n")
    checked = check_params_file(params, "/chair1")
    copy = namespaced_params_file(params, "/chair1", tmp_path / "out", checked)
    assert yaml.safe_load(copy.read_text()) == {
        "chair1/grid": {"ros__parameters": {"safe_height": 1.9}}
    }


def test_a_node_set_in_two_sections_keeps_both_under_a_namespace(tmp_path, capsys):
    """``grid:`` and ``/chair1/grid:`` both reach the grid under ``--namespace chair1``; the
    namespaced copy made one dict key of them and kept only the later: the grid ran on its
    default 1.5 m safe height where the file said 1.9, exit 0. They are merged now (the later
    over the earlier, as rcl applies them); a node written twice under one key, which PyYAML
    read as its last copy, is refused, and so is a key ending in '/', which rcl refuses."""
    import pytest
    import yaml

    from wheelgrid_bringup.demo import main as demo_main
    from wheelgrid_bringup.launcher import check_params_file, namespaced_params_file

    params = tmp_path / "p.yaml"
    params.write_text(
        "grid:\n  ros__parameters: {safe_height: 1.9, density_threshold: 0.2}\n"
        "mapper:\n  ros__parameters: {loop_closure: {enabled: false, min_overlap: 0.2}}\n"
        "/chair1/grid:\n  ros__parameters: {density_threshold: 0.1}\n"
        "/chair1/mapper:\n  ros__parameters: {loop_closure: {min_overlap: 0.3}}\n"
    )
    checked = check_params_file(params, "/chair1")
    copy = namespaced_params_file(params, "/chair1", tmp_path / "out", checked)
    assert yaml.safe_load(copy.read_text()) == {
        "/chair1/grid": {"ros__parameters": {"safe_height": 1.9, "density_threshold": 0.1}},
        "/chair1/mapper": {
            "ros__parameters": {"loop_closure": {"enabled": False, "min_overlap": 0.3}}
        },
    }
    for text, says in (
        (
            "grid:\n  ros__parameters: {safe_height: 1.9}\n"
            "grid:\n  ros__parameters: {density_threshold: 0.1}\n",
            "'grid' is written twice",
        ),
        ("/grid/:\n  ros__parameters: {safe_height: 1.9}\n", "must not end in '/'"),
    ):
        params.write_text(text)
        with pytest.raises(ValueError, match=says):
            check_params_file(params)
    # the demo checks its --params as the launch does, before any node starts
    params.write_text("gird:\n  ros__parameters: {safe_height: 1.7}\n")
    ours = os.environ["ROS_DOMAIN_ID"]
    assert demo_main(["--params", str(params), "--out", str(tmp_path / "demo")]) == 2
    err = capsys.readouterr().err
    assert "reaches no node of the chain" in err and "Traceback" not in err
    # the demo's domain (215-232) given back: it stayed in os.environ, and this test process's
    # later node tests ran in a domain no lock held any more
    assert os.environ["ROS_DOMAIN_ID"] == ours


def test_a_replay_stopped_before_it_started_stops_cleanly():
    """``wheelgrid launch`` opens the bag before it starts the nodes, so a node that dies while
    the chain starts stops a player whose thread never ran: that must not raise (joining an
    unstarted thread does) and so hide the dead node's own message."""
    import rclpy

    from wheelgrid_bringup.replay import BagPlayer
    from wheelgrid_common.testing import rclpy_context

    bag = PKG.parents[1] / "bags" / "paper_room" / "scan"
    with rclpy_context() as ctx:
        node = rclpy.create_node("replay_stop_test", context=ctx)
        try:
            player = BagPlayer(node, bag)
            assert player.total > 0
            player.stop()
            assert player.published == 0
        finally:
            node.destroy_node()


def test_demo_with_a_folder_that_holds_no_bag_says_what_bag_takes(tmp_path, capsys):
    """A wrong --bag said only 'not a rosbag2 bag', which points away from the simulator's
    folder that the demo wants; nothing starts before the check."""
    from wheelgrid_bringup.demo import main as demo_main

    assert demo_main(["--bag", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "not a rosbag2 bag" in err and "--bag takes a `wheelgrid simulate --out` folder" in err
    assert not (tmp_path / "out").exists()


def _bag_with_a_vendor_type(out: Path, clouds: bool = True) -> Path:
    """Two clouds of the bundled bag (or none) and a /battery topic of a type no installation
    has."""
    from rosbags.rosbag2 import Reader, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    with_clouds = clouds
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg("float32 voltage\n", "vendor_msgs/msg/Battery"))
    battery = store.types["vendor_msgs/msg/Battery"](voltage=24.0)
    with Reader(PKG.parents[1] / "bags" / "paper_room" / "scan") as r, Writer(out, version=9) as w:
        clouds = [c for c in r.connections if c.topic == "/iphone/points"]
        if with_clouds:
            cloud_conn = w.add_connection("/iphone/points", clouds[0].msgtype, typestore=store)
        vendor = w.add_connection("/battery", "vendor_msgs/msg/Battery", typestore=store)
        for _, (_, t, raw) in zip(range(2), r.messages(connections=clouds), strict=False):
            if with_clouds:
                w.write(cloud_conn, t, raw)
            w.write(vendor, t, store.serialize_cdr(battery, "vendor_msgs/msg/Battery"))
    return out


def test_launch_and_demo_refuse_what_they_cannot_run_with_one_line_before_any_node(
    tmp_path, capsys
):
    """Found by a review: `--rate nan` was taken (the replay spun a core and sent nothing,
    exit 0), `--duration -1` ended at once with exit 0 and nan never, a --log-dir below a file
    and a bag holding a type this installation lacks ended in tracebacks (exit 1); the demo
    took `--rate 0` and such a bag only after three nodes had started, with a traceback."""
    from wheelgrid_bringup.demo import main as demo_main
    from wheelgrid_bringup.launcher import main as launch_main

    (tmp_path / "afile").write_text("")
    vendor = _bag_with_a_vendor_type(tmp_path / "vendor_bag")
    battery_only = _bag_with_a_vendor_type(tmp_path / "battery_bag", clouds=False)
    quick = ["--no-drive", "--duration", "1", "--log-dir", str(tmp_path / "logs")]
    for argv, says in (
        (["--rate", "nan"], "--rate must be > 0, not nan"),
        (["--duration", "-1"], "--duration must be >= 0 s"),
        (["--duration", "nan"], "--duration must be >= 0 s"),
        (["--log-dir", str(tmp_path / "afile" / "logs")], "Not a directory"),
        # (replayed only when named: it is no sensor data)
        (
            ["--bag", str(vendor), "--topic", "/battery"],
            "/battery holds vendor_msgs/msg/Battery, a message type",
        ),
    ):
        assert launch_main([*quick, *argv]) == 2, argv
        err = capsys.readouterr().err
        assert says in err and "Traceback" not in err, (argv, err)
    for argv, says in (
        (["--rate", "0"], "--rate must be > 0"),
        # (a bag without truth.json needs its cells)
        (["--bag", str(battery_only), "--start", "2,0", "--goal", "6,5"], "no sensor data"),
    ):
        assert demo_main([*argv, "--out", str(tmp_path / "demo")]) == 2, argv
        captured = capsys.readouterr()
        assert says in captured.err and "Traceback" not in captured.err, (argv, captured.err)
        assert not (tmp_path / "demo" / "logs" / "mapper.log").exists()  # no node started


def test_launch_file_gives_the_mapper_time_to_save_as_it_stops():
    """ros2 launch sends SIGTERM 5 s after its SIGINT by default: a mapper cancelling a loop
    closure was killed before its save on exit, as under `wheelgrid launch` before."""
    from wheelgrid_bringup.supervisor import STOP_GRACE_S

    tree = ast.parse((PKG / "launch" / "wheelgrid.launch.py").read_text())
    mappers = [
        n
        for n in ast.walk(tree)
        if isinstance(n, ast.Call)
        and getattr(n.func, "id", "") == "Node"
        and any(
            kw.arg == "name" and getattr(kw.value, "value", "") == "mapper" for kw in n.keywords
        )
    ]
    assert mappers
    for node in mappers:
        timeout = next(kw.value.value for kw in node.keywords if kw.arg == "sigterm_timeout")
        assert float(timeout) == STOP_GRACE_S["mapper"]


def test_a_launch_keeps_the_logs_of_the_runs_before(tmp_path):
    """Each launch opened <node>.log with "wb": the next one over the same --log-dir erased a
    crashed node's traceback. The run before's log is now <node>.log.1, up to .5."""
    import sys

    from wheelgrid_bringup.supervisor import KEPT_LOGS, Supervisor

    for run in range(KEPT_LOGS + 2):
        sup = Supervisor(tmp_path, {})
        sup.start("grid", [sys.executable, "-c", f"print('run {run}')"]).proc.wait(timeout=30)
    said = {p.name: p.read_text().strip() for p in tmp_path.iterdir()}
    last = KEPT_LOGS + 1
    assert said == {"grid.log": f"run {last}"} | {
        f"grid.log.{n}": f"run {last - n}" for n in range(1, KEPT_LOGS + 1)
    }
