"""The ROS plumbing every node relies on, over real DDS on loopback."""

import os
import threading
import time

import numpy as np
import pytest

from wheelgrid_common.pointcloud2 import read_xyz, to_pointcloud2
from wheelgrid_common.qos import MAP_QOS
from wheelgrid_common.testing import call_service, rclpy_context, spin_until

pytestmark = pytest.mark.ros


def test_environment_keeps_dds_on_this_machine():
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert os.environ.get("ROS_DOMAIN_ID")


def test_every_shell_of_a_checkout_shares_one_domain_unless_it_sets_its_own():
    """scripts/env.sh took the shell's pid: `wheelgrid call` in a second terminal was on
    another domain than the nodes the first launched, and saw no service."""
    import subprocess
    from pathlib import Path

    env_sh = Path(__file__).resolve().parents[3] / "scripts" / "env.sh"
    if not (env_sh.parent.parent / "install" / "setup.sh").exists():
        pytest.skip("no colcon install space next to scripts/env.sh")

    def domain(preset: str) -> str:
        cmd = f"{preset}; . '{env_sh}' && echo $ROS_DOMAIN_ID"
        return subprocess.run(
            ["bash", "-c", cmd], capture_output=True, text=True, check=True
        ).stdout.split()[-1]

    first, second = domain("unset ROS_DOMAIN_ID"), domain("unset ROS_DOMAIN_ID")
    assert first == second and 1 <= int(first) <= 100
    assert domain("export ROS_DOMAIN_ID=42") == "42"


def test_map_qos_delivers_to_a_late_subscriber():
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2

    pts = np.arange(30, dtype=np.float64).reshape(10, 3)
    with rclpy_context() as ctx:
        pub_node = Node("wg_test_pub", context=ctx)
        sub_node = Node("wg_test_sub", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(pub_node)
        ex.add_node(sub_node)
        pub = pub_node.create_publisher(PointCloud2, "/wg_test/map_cloud", MAP_QOS)
        pub.publish(to_pointcloud2(pts, "map"))
        got = []
        sub_node.create_subscription(PointCloud2, "/wg_test/map_cloud", got.append, MAP_QOS)
        assert spin_until(ex, lambda: bool(got), timeout=10.0)
        np.testing.assert_allclose(read_xyz(got[0]), pts)
        ex.shutdown()
        pub_node.destroy_node()
        sub_node.destroy_node()


def test_call_service_asks_again_and_keeps_the_slow_first_answer():
    """A request is re-sent while no answer comes, and an answer to an earlier one still counts
    (a save slower than the retry period); with no server at all the caller gets None."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_srvs.srv import Trigger

    calls: list[float] = []

    def slow_first(_req, res):
        calls.append(time.monotonic())
        if len(calls) == 1:
            time.sleep(1.5)
        res.success, res.message = True, f"answer {len(calls)}"
        return res

    with rclpy_context() as server_ctx, rclpy_context() as client_ctx:
        server = Node("wg_test_server", context=server_ctx)
        server.create_service(Trigger, "/wg_test/slow", slow_first)
        server_ex = SingleThreadedExecutor(context=server_ctx)
        server_ex.add_node(server)
        spinner = threading.Thread(target=server_ex.spin, daemon=True)
        spinner.start()
        node = Node("wg_test_client", context=client_ctx)
        ex = SingleThreadedExecutor(context=client_ctx)
        ex.add_node(node)
        try:
            client = node.create_client(Trigger, "/wg_test/slow")
            assert spin_until(ex, client.service_is_ready, timeout=20.0)
            answer = call_service(ex, client, Trigger.Request, timeout=20.0, attempt=0.5)
            assert answer is not None and answer.message == "answer 1"
            # asked again while the first was being served (the server gets to it after)
            assert spin_until(ex, lambda: len(calls) >= 2, timeout=10.0)

            nobody = node.create_client(Trigger, "/wg_test/nobody")
            started = time.monotonic()
            assert call_service(ex, nobody, Trigger.Request, timeout=1.0, attempt=0.3) is None
            assert time.monotonic() - started < 5.0
        finally:
            server_ex.shutdown()
            spinner.join(timeout=5.0)
            ex.shutdown()
            node.destroy_node()
            server.destroy_node()


def test_the_fastdds_profile_is_used_only_where_nothing_else_was_chosen(monkeypatch):
    """Every wheelgrid process runs Fast DDS with a 16 MB shared-memory segment and UDP on
    127.0.0.1 (only the bridge did: a bag player's 786 kB clouds went out as UDP fragments,
    and on a loaded machine more than half of them never arrived, bench/bench_transport.py);
    never over a choice the user made, nor where /dev/shm cannot hold the segments."""
    import shutil
    from collections import namedtuple

    from wheelgrid_common import ros_env

    base = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
    roomy = namedtuple("usage", "total used free")(2**34, 0, 2**34)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: roomy)
    assert ros_env.fastdds_profile(base) == ros_env.FASTDDS_PROFILE
    assert ros_env.FASTDDS_PROFILE.is_file()
    for chosen in (
        {"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"},
        {"FASTDDS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"},
        {"WHEELGRID_FASTDDS_PROFILE": "0"},
        {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"},
        {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"},  # a remote RViz must stay reachable
        {"ROS_STATIC_PEERS": "192.168.1.7"},
    ):
        assert ros_env.fastdds_profile({**base, **chosen}) is None, chosen
    env = dict(base, ROS_LOG_DIR="/tmp/wheelgrid-test-profile-log")
    assert ros_env.configure_ros_env(env)["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(
        ros_env.FASTDDS_PROFILE
    )
    small = namedtuple("usage", "total used free")(2**26, 0, 2**26)  # a container's 64 MB
    monkeypatch.setattr(shutil, "disk_usage", lambda path: small)
    assert ros_env.fastdds_profile(base) is None


def test_a_process_started_with_the_profile_gets_the_large_shared_memory_segment():
    """Fast DDS reads a profile it cannot parse as no profile at all, silently: the segment
    it makes is what shows the file took effect."""
    import subprocess
    import sys
    from pathlib import Path

    from wheelgrid_common.ros_env import FASTDDS_PROFILE, child_env, fastdds_profile
    from wheelgrid_common.testing import managed_process

    env = child_env()
    if env.get("FASTRTPS_DEFAULT_PROFILES_FILE") == str(FASTDDS_PROFILE):
        del env["FASTRTPS_DEFAULT_PROFILES_FILE"]  # ours, set by configure_ros_env
    if fastdds_profile(env) is None:
        pytest.skip("no Fast DDS profile here (another RMW, a user's profile, or a small /dev/shm)")
    shm = Path("/dev/shm")
    # SIGINT's default handler restored first: a job run in the background of a script (as CI
    # runs the suite) inherits SIGINT ignored, and this child, which never spins, then sat out
    # the 7 s of managed_process's SIGINT grace twice (14.8 s in CI, 0.7 s at a terminal)
    code = (
        "import signal; signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "from wheelgrid_common.ros_env import configure_ros_env; configure_ros_env()\n"
        "import rclpy, sys; from rclpy.node import Node; from std_msgs.msg import Bool\n"
        "rclpy.init(); n = Node('profile_probe'); n.create_publisher(Bool, '/probe', 1)\n"
        "print('up', flush=True); sys.stdin.readline()\n"
    )

    def new_segments(switch: str) -> list[int]:
        """Sizes of the shared-memory files the child maps. Read from its own
        /proc/PID/maps: files that appeared in /dev/shm meanwhile were once counted, and any
        other DDS process started then (a second test run) added its 16 MB segment to the
        count of the child without the profile."""
        env = child_env(WHEELGRID_FASTDDS_PROFILE=switch)
        env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
        # managed_process stops the child whatever happens here (a readline that fails)
        with managed_process(
            [sys.executable, "-c", code], env=env, stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, text=True,
        ) as proc:  # fmt: skip
            assert proc.stdout is not None and proc.stdout.readline().strip() == "up"
            maps = Path(f"/proc/{proc.pid}/maps").read_text().splitlines()
            mapped = {ln.split(maxsplit=5)[5] for ln in maps if len(ln.split(maxsplit=5)) == 6}
            files = [Path(m) for m in mapped if m.startswith(f"{shm}/")]
            return [f.stat().st_size for f in files if f.is_file()]

    assert max(new_segments("1"), default=0) >= 16 * 1024 * 1024
    assert max(new_segments("0"), default=0) < 16 * 1024 * 1024


def test_a_number_written_1e_4_reads_as_rcl_reads_it(tmp_path):
    """One file serves ``--params-file`` (rcl) and ``--config`` (PyYAML, YAML 1.1): rcl read
    ``1e-4`` as a double, PyYAML as a string, and ``wheelgrid map --config`` refused the
    file the mapper node ran with. A quoted one stays a string in both."""
    from rclpy.node import Node

    from wheelgrid_common.params import field, load_yaml

    text = (
        "mapper:\n  ros__parameters:\n    a: 1e-4\n    b: -2E+3\n    c: 1.5e1\n    d: '1e-4'\n"
        "    e: 1_0e5\n    f: -1e400\n"  # text to rcl: an underscore, an overflow
    )
    (tmp_path / "p.yaml").write_text(text)
    with rclpy_context() as ctx:
        node = Node(
            "mapper",
            context=ctx,
            cli_args=["--ros-args", "--params-file", str(tmp_path / "p.yaml")],
            automatically_declare_parameters_from_overrides=True,
        )
        try:
            by_rcl = {k: node.get_parameter(k).value for k in "abcdef"}
        finally:
            node.destroy_node()
    assert by_rcl == {"a": 1e-4, "b": -2000.0, "c": 15.0, "d": "1e-4", "e": "1_0e5", "f": "-1e400"}

    from dataclasses import dataclass

    @dataclass
    class Cfg:
        a: float = field(0.0, "a")
        b: float = field(0.0, "b")
        c: float = field(0.0, "c")
        d: str = field("", "d")
        e: str = field("", "e")
        f: str = field("", "f")

    assert load_yaml(Cfg, tmp_path / "p.yaml") == Cfg(**by_rcl)


def test_tf2_is_available_only_where_its_type_support_loads(monkeypatch):
    """A tf2_msgs that imports but whose C type support does not load (a partial build) was
    taken for available, and the mapper died creating its /tf publisher; set-up said "the
    mapper publishes /tf". It is unavailable now, and the mapper runs on without /tf."""
    from wheelgrid_common.ros_env import tf2_available

    if not tf2_available():
        pytest.skip("tf2_msgs not importable here")
    from tf2_msgs.msg import TFMessage

    def broken(cls):
        raise ImportError("Could not import 'rosidl_typesupport_c' for package 'tf2_msgs'")

    monkeypatch.setattr(TFMessage.__class__, "__import_type_support__", classmethod(broken))
    assert not tf2_available()
    from wheelgrid_common.ros_env import tf2_problem

    problem = tf2_problem()  # what the mapper says: not "not importable", which it is
    assert problem is not None and "importable but its type support does not load" in problem


def test_a_domain_held_by_another_process_is_passed_over_until_that_process_ends(tmp_path):
    """Two demos run at once picked the same domain and each mapped the other's frames: a
    domain is claimed with a lock file that another process's claim sees, and that ends with
    the process however it ends (here killed)."""
    import subprocess
    import sys

    from wheelgrid_common.ros_env import claim_domain

    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import sys, time; from pathlib import Path; "
         "from wheelgrid_common.ros_env import claim_domain; "
         f"print(claim_domain([215], Path({str(tmp_path)!r}))[0], flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "215"
        got = claim_domain([215, 216], tmp_path)
        assert got is not None and got[0] == 216  # 215 is held: the next one
        assert claim_domain([215, 216], tmp_path) is None  # both held (216 by this process)
        os.close(got[1])
        again = claim_domain([215, 216], tmp_path)
        assert again is not None and again[0] == 216  # closed: free again
        os.close(again[1])
    finally:
        holder.kill()
        holder.wait()
    freed = claim_domain([215], tmp_path)  # the killed holder left no stale claim behind
    assert freed is not None and freed[0] == 215 and freed[1] >= 0
    os.close(freed[1])


def test_this_test_process_holds_its_domain_and_not_the_shells():
    """Two test runs at once drew the same random domain and failed each other's node tests
    (5 of 21 each), and a bare pytest after scripts/env.sh ran in the checkout's domain, a
    live `wheelgrid launch`'s (a review): each test process claims its own."""
    from wheelgrid_common.ros_env import claim_domain

    domain = int(os.environ["ROS_DOMAIN_ID"])
    assert 1 <= domain <= 100
    assert claim_domain([domain]) is None  # held, by this process's conftest


def test_a_managed_child_dies_with_a_test_process_killed_outright():
    """A node a test started outlived a pytest killed with SIGKILL by minutes, in a session of
    its own that nothing else reached (a review)."""
    import subprocess
    import sys

    from wheelgrid_common.ros_env import child_env

    code = (
        "import sys, time\n"
        "from wheelgrid_common.testing import managed_process\n"
        "with managed_process([sys.executable, '-c', 'import time; time.sleep(120)']) as p:\n"
        "    print(p.pid, flush=True)\n"
        "    time.sleep(120)\n"
    )
    parent = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=child_env()
    )
    assert parent.stdout is not None
    child = int(parent.stdout.readline())
    try:
        parent.kill()
        parent.wait()
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            try:
                with open(f"/proc/{child}/stat") as f:
                    if f.read().split(") ")[1].startswith("Z"):
                        break  # dead, not yet reaped by its new parent
            except FileNotFoundError:
                break
            time.sleep(0.05)
        else:
            pytest.fail("the managed child outlived its killed parent")
    finally:
        with __import__("contextlib").suppress(ProcessLookupError):
            os.kill(child, 9)


def test_an_rmw_that_is_not_installed_is_named(tmp_path):
    """A shell left with rmw_cyclonedds_cpp from another ROS install made the suite exit 102
    without a word (rclpy's first init): conftest and scripts/env.sh look for its library."""
    from wheelgrid_common.ros_env import rmw_missing

    assert rmw_missing({}) == "" and rmw_missing({"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}) == ""
    env = {"RMW_IMPLEMENTATION": "rmw_nosuch_cpp", "LD_LIBRARY_PATH": str(tmp_path)}
    assert "rmw_nosuch_cpp is not installed here" in rmw_missing(env)
    (tmp_path / "librmw_nosuch_cpp.so").touch()
    assert rmw_missing(env) == ""


def test_a_domain_id_that_is_no_domain_is_named_and_the_launch_and_call_refuse_it(monkeypatch):
    """ROS_DOMAIN_ID=abc ended `wheelgrid launch` and `wheelgrid call` in rclpy's traceback,
    250 in Fast DDS's "port number is too high" with no word of the variable, and -1 ran the
    chain in domain 0 (a review): each is one line and exit 2 now, before DDS starts."""
    from wheelgrid_bringup import call, launcher
    from wheelgrid_common.ros_env import domain_id_problem

    assert domain_id_problem({}) == "" and domain_id_problem({"ROS_DOMAIN_ID": "232"}) == ""
    for bad in ("abc", "250", "-1", "1.5"):
        assert "is not a domain" in domain_id_problem({"ROS_DOMAIN_ID": bad}), bad
    monkeypatch.setenv("ROS_DOMAIN_ID", "abc")
    assert launcher.main(["--no-drive", "--duration", "1"]) == 2
    assert call.main(["/mapper/save_map"]) == 2


def test_env_sh_refuses_a_path_with_a_space_and_an_rmw_it_lacks(tmp_path):
    """A checkout at a path with a space set up well, then nothing of wheelgrid was found
    (colcon's setup scripts split the path); an RMW left from another ROS install that this
    one lacks made rclpy exit 102 without a word (a review)."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    if not (root / "install" / "setup.sh").exists():
        pytest.skip("no colcon install space next to scripts/env.sh")
    spaced = tmp_path / "a checkout"
    spaced.symlink_to(root)
    run = subprocess.run(
        ["bash", "-c", f". '{spaced}/scripts/env.sh' && echo sourced"],
        capture_output=True,
        text=True,
    )
    assert run.returncode != 0 and "sourced" not in run.stdout
    assert "has a space in it" in run.stderr
    run = subprocess.run(
        ["bash", "-c", f"export RMW_IMPLEMENTATION=rmw_nosuch_cpp; . '{root}/scripts/env.sh' "
         "&& echo $RMW_IMPLEMENTATION"],
        capture_output=True,
        text=True,
    )  # fmt: skip
    assert run.stdout.split()[-1] == "rmw_fastrtps_cpp", run.stderr
    assert "rmw_nosuch_cpp is not installed here" in run.stderr


def test_a_stopped_process_is_continued_so_it_can_stop_cleanly(tmp_path):
    """A node frozen with SIGSTOP handled neither SIGINT nor SIGTERM: the launcher waited out
    the grace, SIGKILLed the mapper, and its scan was never saved on exit (a review). Each
    signal now comes with SIGCONT, as systemd sends it."""
    import signal
    import subprocess
    import sys

    from wheelgrid_common.testing import managed_process, stop_process

    saved = tmp_path / "saved"
    code = (
        "import signal, sys, time\n"
        "def bye(*_):\n"
        f"    open({str(saved)!r}, 'w').write('saved')\n"
        "    sys.exit(0)\n"
        "signal.signal(signal.SIGINT, bye)\n"
        "print('ready', flush=True)\n"
        "time.sleep(120)\n"
    )
    with managed_process([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True) as p:
        assert p.stdout is not None and p.stdout.readline().strip() == "ready"
        os.kill(p.pid, signal.SIGSTOP)
        t0 = time.monotonic()
        assert stop_process(p, grace=10.0) == 0
        assert time.monotonic() - t0 < 5.0 and saved.read_text() == "saved"
