"""`wheelgrid launch` leaves no node behind however it ends.

The nodes run in sessions of their own (so that a terminal's Ctrl-C reaches only the
launcher, which stops them in order). A launcher ended by SIGHUP (its terminal closed, an ssh
session dropped) died at once, without its clean-up: mapper, grid, planner and drive ran on,
orphaned, the drive holding the chair's serial port and feeding its watchdog. A launcher that
was SIGKILLed (the OOM killer, `kill -9`) left them all the same.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from wheelgrid_common.testing import (
    chain_params,
    dying_with_this_process,
    stop_process,
    wheelgrid_command,
)

pytestmark = [pytest.mark.ros]

NODES = ("mapper", "grid", "planner")


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in ("Z", "X")  # a zombie no one reaped has stopped


def _launch(
    tmp_path: Path, hangup: object = signal.SIG_DFL, domain: int | None = None
) -> tuple[subprocess.Popen[str], dict[str, int], list[str]]:
    """The launcher with SIGHUP as a terminal's child has it (``hangup``; SIG_IGN: under
    ``nohup``), whatever the test run's own is: a run under nohup passed it on ignored. In
    ``domain`` where one is given, else in the test's."""
    params = chain_params(tmp_path, tmp_path / "out")
    cmd = wheelgrid_command(
        "launch", "--no-drive", "--params", str(params), "--log-dir", str(tmp_path / "logs")
    )
    proc = subprocess.Popen(
        dying_with_this_process(cmd),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGHUP, hangup),  # type: ignore[arg-type]
        env=None if domain is None else {**os.environ, "ROS_DOMAIN_ID": str(domain)},
    )
    lines: list[str] = []
    threading.Thread(
        target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True
    ).start()
    pids: dict[str, int] = {}
    try:
        deadline = time.monotonic() + 60.0
        while len(pids) < len(NODES) and time.monotonic() < deadline and proc.poll() is None:
            for ln in list(lines):
                m = re.match(r"launch: started (\w+) \(pid (\d+)", ln)
                if m:
                    pids[m.group(1)] = int(m.group(2))
            time.sleep(0.1)
        assert set(pids) == set(NODES), "".join(lines)
        # the status line comes once the nodes are running
        while not any(ln.startswith("[") for ln in lines) and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(2.0)  # the nodes past their start-up, rclpy's signal handlers in place
    except BaseException:
        # the callers' try/finally is not entered yet: stop the launcher and any node it had
        # started here, or they run on past the test (a node short, or Ctrl-C in the wait)
        stop_process(proc)
        _cleanup(pids)
        raise
    return proc, pids, lines


def _gone(pids: dict[str, int], timeout: float) -> list[str]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and any(_alive(p) for p in pids.values()):
        time.sleep(0.1)
    return [name for name, pid in pids.items() if _alive(pid)]


def _cleanup(pids: dict[str, int]) -> None:
    for pid in pids.values():
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)


def test_a_launcher_whose_terminal_closes_stops_every_node(tmp_path):
    proc, pids, lines = _launch(tmp_path)
    try:
        # a second terminal reaches the chain only on its domain: the launcher says which
        domain = f"launch: ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']} "
        assert any(ln.startswith(domain) for ln in lines), "".join(lines[:5])
        os.kill(proc.pid, signal.SIGHUP)
        proc.wait(timeout=60)
        left = _gone(pids, 10.0)
        assert not left, f"left running after SIGHUP: {left}\n" + "".join(lines[-10:])
        assert any(ln.startswith("launch: stopped") for ln in lines), "".join(lines[-10:])
    finally:
        stop_process(proc)
        _cleanup(pids)


def _hold_in_tracing_stop(pid: int) -> None:
    """Stop ``pid`` as a debugger does (PTRACE_SEIZE, PTRACE_INTERRUPT): unlike SIGSTOP, no
    SIGCONT resumes it and it handles no signal; SIGKILL still ends it."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    libc.ptrace.argtypes = [ctypes.c_long, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p]
    for request in (0x4206, 0x4207):  # PTRACE_SEIZE, PTRACE_INTERRUPT
        if libc.ptrace(request, pid, None, None) != 0:
            pytest.skip(f"ptrace refused here ({os.strerror(ctypes.get_errno())})")


def test_a_node_that_must_be_killed_at_the_stop_makes_the_launch_fail(tmp_path):
    """A node that handles neither its SIGINT nor its SIGTERM (here: held as a debugger holds
    it) is killed 7 s on; the launcher said "stopped grid (-9)" and exited 0, so a script never
    learned that a node had not done what it does on its way out."""
    proc, pids, lines = _launch(tmp_path)
    try:
        _hold_in_tracing_stop(pids["grid"])
        os.kill(proc.pid, signal.SIGINT)
        # a traced process's end reaches its tracer first: reaped here, its parent (the
        # launcher) then sees it killed
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            _, status = os.waitpid(pids["grid"], os.WNOHANG | 0x40000000)  # __WALL
            if status and not os.WIFSTOPPED(status):
                break
            time.sleep(0.05)
        assert proc.wait(timeout=60) == 1, "".join(lines[-10:])
        left = _gone(pids, 10.0)
        assert not left, f"left running: {left}"
        said = [ln for ln in lines if "did not stop cleanly" in ln]
        assert len(said) == 1, "".join(lines[-10:])
        assert said[0].startswith("wheelgrid launch: grid (exit -9) did not stop cleanly: see ")
    finally:
        stop_process(proc)
        _cleanup(pids)


def test_a_frozen_node_is_continued_and_stops_cleanly(tmp_path):
    """A node frozen with SIGSTOP (Ctrl-Z, a debugger let go) handled neither SIGINT nor
    SIGTERM: it was killed 7 s on, and a frozen mapper's scan was never saved on exit (a
    review). Each stop signal now comes with SIGCONT, and it stops as any other."""
    proc, pids, lines = _launch(tmp_path)
    try:
        os.kill(pids["grid"], signal.SIGSTOP)
        os.kill(proc.pid, signal.SIGINT)
        assert proc.wait(timeout=60) == 0, "".join(lines[-10:])
        assert not _gone(pids, 10.0)
        assert not any("did not stop cleanly" in ln for ln in lines), "".join(lines[-10:])
    finally:
        stop_process(proc)
        _cleanup(pids)


def test_a_launcher_killed_outright_takes_its_nodes_with_it(tmp_path):
    proc, pids, _ = _launch(tmp_path)
    try:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        left = _gone(pids, 30.0)
        assert not left, f"left running after the launcher was killed: {left}"
    finally:
        stop_process(proc)
        _cleanup(pids)


def test_the_mapper_is_given_time_to_save_its_map_as_the_chain_stops(tmp_path):
    """The mapper saves an unsaved map as it stops, after up to 10 s for its worker to let go
    (a loop closure being cancelled) and 5 s for the map's lock. The launcher gave every node
    5 s after its SIGINT, then SIGTERM, then SIGKILL 2 s on: a Ctrl-C during a closure killed
    the mapper before its save, and the scan was lost. A stand-in mapper that needs 7.5 s to
    save (and, as an rclpy node, outlives SIGTERM) now gets them."""
    from wheelgrid_bringup.supervisor import Supervisor

    saved = tmp_path / "saved"
    # SIGINT taken whatever the child inherited, as rclpy's handler takes it: a pytest-xdist
    # worker, or a script's background job, hands its children SIGINT ignored
    code = (
        "import signal, sys, time\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
        "try:\n"
        "    time.sleep(60)\n"
        "except KeyboardInterrupt:\n"
        "    time.sleep(7.5)\n"
        f"    open({str(saved)!r}, 'w').write('map')\n"
    )
    sup = Supervisor(tmp_path / "logs")
    sup.start("mapper", [sys.executable, "-c", code])
    time.sleep(1.0)  # the child is in its sleep
    t0 = time.monotonic()
    codes = sup.stop_all()
    assert saved.exists(), f"killed after {time.monotonic() - t0:.1f} s, before its save"
    assert codes["mapper"] == 0


def test_a_node_stopped_while_it_is_still_importing_ends_cleanly(tmp_path):
    """A Ctrl-C half a second after start-up reached the nodes inside their imports: a
    KeyboardInterrupt traceback in every node's log and "did not stop cleanly", exit 1 (a
    review). A node with nothing yet to save nor a chair to stop ends with status 0."""
    from wheelgrid_bringup.supervisor import child_code
    from wheelgrid_common.ros_env import child_env

    (tmp_path / "slow_node.py").write_text(
        "import time\nprint('importing', flush=True)\ntime.sleep(60)\ndef main():\n    return 0\n"
    )
    env = child_env()
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), env.get("PYTHONPATH", "")])
    proc = subprocess.Popen(
        [sys.executable, "-c", child_code("slow_node", "main")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        start_new_session=True,
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "importing"
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=10)
    finally:
        stop_process(proc)
    assert proc.returncode == 0 and "Traceback" not in err, err


def test_a_node_stopped_before_its_interpreter_has_started_ends_cleanly(tmp_path):
    """Before the code above runs, the interpreter imports its site (the venv's bootstrap): a
    Ctrl-C there was a traceback, exit 1, or death by the signal, -2 (a review: a launch
    stopped 0.2-0.5 s after its start, "did not stop cleanly"). The supervisor starts each
    node with SIGINT blocked, and the node lets it in once its quiet handler is set."""
    from wheelgrid_bringup.supervisor import Supervisor, child_code
    from wheelgrid_common.ros_env import child_env

    (tmp_path / "quick_node.py").write_text("def main():\n    return 0\n")
    env = child_env()
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), env.get("PYTHONPATH", "")])
    sup = Supervisor(tmp_path / "log", env)
    codes = []
    for i in range(5):  # the signal within microseconds of the fork: still in start-up
        managed = sup.start(f"n{i}", [sys.executable, "-c", child_code("quick_node", "main")])
        managed.proc.send_signal(signal.SIGINT)
        codes.append(managed.proc.wait(timeout=30))
        assert "Traceback" not in managed.log_path.read_text()
    assert codes == [0] * 5
    assert signal.pthread_sigmask(signal.SIG_BLOCK, set()) == set()  # ours given back


def test_a_launch_holds_its_domain_so_that_no_test_process_claims_it(tmp_path):
    """Each test process claims a domain no other wheelgrid process holds, but only demos
    held theirs: a test run beside a `wheelgrid launch` could land on its graph, drive
    included (a review). The launcher holds its domain while it runs."""
    from wheelgrid_common.ros_env import claim_domain

    own = int(os.environ["ROS_DOMAIN_ID"])
    got = claim_domain(d for d in range(1, 101) if d != own)
    assert got is not None
    domain, fd = got
    os.close(fd)  # free again, for the launch to take
    proc, pids, lines = _launch(tmp_path, domain=domain)
    try:
        assert any(ln.startswith(f"launch: ROS_DOMAIN_ID={domain} ") for ln in lines), lines
        assert claim_domain([domain]) is None  # the launch holds it
        os.kill(proc.pid, signal.SIGINT)
        assert proc.wait(timeout=60) == 0, "".join(lines[-10:])
    finally:
        stop_process(proc)
        _cleanup(pids)
    again = claim_domain([domain])  # let go with the launch
    assert again is not None and again[0] == domain
    os.close(again[1])
