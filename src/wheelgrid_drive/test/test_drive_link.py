"""The pyserial link against the simulated controller over a real pty."""

import math
import os
import signal
import sys
import textwrap
import threading
import time

import pytest

from wheelgrid_common.ros_env import child_env
from wheelgrid_common.testing import managed_process
from wheelgrid_drive import protocol as proto
from wheelgrid_drive.actions import YAW, plan_steps
from wheelgrid_drive.link import LinkAbortedError, LinkError, MotorLink
from wheelgrid_drive.runner import run_steps


def moves(sim):
    return [(e.seq, e.detail) for e in sim.events if e.what == "move"]


def test_table_ii_route_is_executed_exactly(make_sim, make_link):
    # Start cell (2, 0) of a 1.2 m grid whose row 0 spans y in [-1.2, 0]: centre (0.6, -3.0).
    sim = make_sim(pose=(0.6, -3.0, YAW["down"]))
    link = make_link(sim.slave_path)
    steps = plan_steps((2, 0), ["right"] * 5 + ["down"] * 4, "down")
    records = []
    result = run_steps(
        link, steps, distance_m=1.2, speed_kmh=3.0, on_step=lambda s, r: records.append(r)
    )
    assert result.ok and result.done == 9
    assert [d for _, d in moves(sim)] == ["LEFT_FORWARD"] + ["FORWARD"] * 4 + ["RIGHT_FORWARD"] + [
        "FORWARD"
    ] * 3
    assert [r["ack"] for r in records] == ["ACK"] * 9
    # Each move ends at the centre of its destination cell (no noise configured).
    for step, rec in zip(steps, records, strict=True):
        r, c = step.dst
        assert rec["pose"] == pytest.approx([(c + 0.5) * 1.2, -(r + 0.5) * 1.2], abs=0.01)
    st = link.status()
    assert st.result == proto.Result.DONE and not st.moving
    assert math.isclose(st.yaw, YAW["down"], abs_tol=0.01)
    # Every frame arrived intact and no move was sent twice.
    assert st.rx_errors == 0 and len(moves(sim)) == 9


def test_lost_reply_is_retried_and_the_move_runs_once(make_sim, make_link):
    sim = make_sim()
    link = make_link(sim.slave_path, heartbeat=False)
    sim.drop_tx_next = 1  # the ACK of the FORWARD is lost on the wire
    seq, st = link.execute("FORWARD", 1.2, 3.0)
    assert st.result == proto.Result.DONE
    assert link.stats.retries >= 1 and link.stats.timeouts >= 1
    assert moves(sim) == [(seq, "FORWARD")]  # the retry was recognised, not executed again
    assert st.x == pytest.approx(1.2, abs=0.01)


def test_garbled_reply_is_logged_as_a_failure_and_retried(make_sim, make_link):
    sim = make_sim()
    link = make_link(sim.slave_path, heartbeat=False)
    sim.corrupt_tx_next = 1
    st = link.status()
    assert st.state == proto.State.IDLE
    assert link.stats.garbled == 1 and link.stats.retries >= 1
    assert any(kind == "garbled" for kind, _ in link.events)


def test_lost_requests_exhaust_retries_and_raise(make_sim, make_link):
    sim = make_sim()
    link = make_link(sim.slave_path, heartbeat=False, retries=2)
    sim.drop_rx_next = 3  # the request and both retries are lost
    with pytest.raises(LinkError, match="3 attempt"):
        link.status()
    assert link.stats.timeouts == 3


def test_nak_busy_fails_the_move_and_stops_the_chair(make_sim, make_link):
    sim = make_sim(time_scale=1.0)
    link = make_link(sim.slave_path)
    link.move("FORWARD", 1.2, 3.0)  # 1.4 s of driving
    with pytest.raises(LinkError, match="BUSY"):
        link.move("LEFT_FORWARD", 1.2, 3.0)
    st = link.status()
    assert not st.moving and st.result == proto.Result.STOPPED
    assert any(kind == "nak" for kind, _ in link.events)


def test_controller_refuses_speed_over_cap_even_from_a_rogue_host(make_sim, make_link):
    sim = make_sim()
    link = make_link(sim.slave_path, heartbeat=False)
    too_fast = (1200).to_bytes(2, "big") + (proto.MAX_SPEED_MM_S + 1).to_bytes(2, "big")
    frame = link.request(proto.MsgType.FORWARD, too_fast)
    assert frame.type == proto.MsgType.NAK and frame.payload[1] == proto.Nak.SPEED_OVER_CAP
    assert moves(sim) == []


def test_abort_stops_a_running_move(make_sim, make_link, wait):
    import threading

    sim = make_sim(time_scale=1.0)
    link = make_link(sim.slave_path)
    abort = threading.Event()
    steps = plan_steps((0, 0), ["right", "right"], "right")
    out = {}
    th = threading.Thread(
        target=lambda: out.update(
            r=run_steps(link, steps, distance_m=1.2, speed_kmh=3.0, abort=abort)
        )
    )
    th.start()
    assert wait(lambda: sim.state != proto.State.IDLE, 3.0)
    abort.set()
    th.join(5.0)
    assert out["r"].aborted and out["r"].done == 0
    assert sim.result == proto.Result.STOPPED and sim.state == proto.State.IDLE
    assert next(e.detail for e in sim.events if e.what == "stop") == "STOP frame"
    with pytest.raises(LinkAbortedError):
        link.execute("FORWARD", 1.2, 3.0, abort=abort)


def test_a_stray_frame_start_on_the_line_does_not_hold_back_the_stop(make_sim, make_link, wait):
    """Line noise of ``A5 40`` (a SOF and a LEN of 64) just before the e-stop's STOP: the
    controller waited for a 70-byte frame, the STOP went unacknowledged and the watchdog
    stopped the chair 0.4 s later, 34 cm on at 3 km/h. The cut-off frame is given up."""
    sim = make_sim(time_scale=1.0)
    link = make_link(sim.slave_path)
    link.move("FORWARD", 2.0, 3.0)
    assert wait(lambda: sim.state != proto.State.IDLE, 3.0)
    with link._write_lock:  # noise on the wire, as a UART glitch makes it
        link._ser.write(bytes([proto.SOF, 0x40]))
        link._ser.flush()
    assert link.stop(), "the STOP was not acknowledged"
    assert wait(lambda: sim.state == proto.State.IDLE, 1.0)
    assert sim.result == proto.Result.STOPPED  # by the STOP, not by the watchdog
    assert any(e.what == "rx_error" and "frame cut off" in e.detail for e in sim.events)


HOST = textwrap.dedent("""
    import sys, time
    from wheelgrid_drive.link import MotorLink
    link = MotorLink(sys.argv[1]).open()
    link.start_heartbeat()
    link.move("FORWARD", 2.0, 0.5)  # 14 s of slow driving: the host will die long before
    print("moving", flush=True)
    time.sleep(60)
""")


def test_controller_stops_by_itself_when_the_host_dies(make_sim, wait, tmp_path):
    sim = make_sim(time_scale=1.0, heartbeat_timeout=0.5)
    script = tmp_path / "host.py"
    script.write_text(HOST)
    with managed_process(
        [sys.executable, str(script), sim.slave_path], env=child_env(), stdout=-1, text=True
    ) as proc:
        assert proc.stdout.readline().strip() == "moving"
        assert wait(lambda: sim.state == proto.State.DRIVING, 2.0)
        # Heartbeats flow while the host lives: the move keeps running past the timeout.
        wait(lambda: False, 0.8)
        assert sim.state == proto.State.DRIVING
        os.killpg(proc.pid, signal.SIGKILL)  # the host dies without a word
        assert wait(lambda: sim.state == proto.State.IDLE, 3.0)
    dog = [e for e in sim.events if e.what == "watchdog"]
    assert len(dog) == 1 and sim.result == proto.Result.WATCHDOG
    assert sim.flags & proto.FLAG_WATCHDOG
    # The controller's own measure of the silence when it stopped: just over the timeout
    # (it checks every 5 ms tick), never a multiple of it.
    silence = float(dog[0].detail)
    print(f"watchdog stopped the motors after {silence * 1000:.1f} ms of silence")
    # (the detail is rounded to the microsecond: a silence a fraction of one past the timeout
    # reads as equal to it)
    assert 0.5 <= silence < 0.5 + 0.25


def test_vanished_port_is_reported_and_recovered(make_sim, make_link, wait, tmp_path):
    port = str(tmp_path / "ttyWG")
    sim1 = make_sim(link=port)
    link = make_link(port, reconnect_period=0.1)
    assert link.status().state == proto.State.IDLE
    sim1.vanish()
    assert wait(lambda: not link.connected, 3.0)
    assert wait(lambda: any(kind == "vanished" for kind, _ in link.events), 1.0)
    with pytest.raises(LinkError):
        link.move("FORWARD", 1.2, 3.0)  # never pretends to move without a controller
    sim2 = make_sim(link=port)  # the adapter comes back under the same name
    assert wait(lambda: link.connected and link.stats.reconnects == 1, 3.0)
    assert wait(lambda: any(e.what == "rx" for e in sim2.events), 2.0)
    first = next(e for e in sim2.events if e.what == "rx")
    assert first.detail == "STOP"  # the first word after a reconnection is STOP
    seq, st = link.execute("FORWARD", 1.2, 3.0)
    assert st.result == proto.Result.DONE and moves(sim2) == [(seq, "FORWARD")]


def test_unopenable_port_is_an_error(tmp_path):
    with pytest.raises(LinkError, match="cannot open"):
        MotorLink(str(tmp_path / "nothing")).open()


def test_a_new_move_is_never_taken_for_a_retry_after_the_seq_wraps(make_sim, make_link):
    """Identical FORWARDs whose SEQ comes round again (256 requests later) both run."""
    sim = make_sim(time_scale=50.0)
    link = make_link(sim.slave_path, heartbeat=False)
    first, _ = link.execute("FORWARD", 0.05, 3.0)
    while (link._seq + 1) & 0xFF != first:  # the next request would reuse the move's SEQ
        link.status()
    second, _ = link.execute("FORWARD", 0.05, 3.0)
    assert second != first
    assert [e.detail for e in sim.events if e.what == "move"] == ["FORWARD", "FORWARD"]
    assert abs(sim.status().x - 0.10) < 0.01


def test_a_second_host_process_is_not_taken_for_a_retry_of_the_first(make_sim, make_link):
    """Each host process numbers its frames from 1; the controller remembers the last move it
    accepted from anyone. Two `wheelgrid drive` runs with the same one-cell plan sent the same
    first FORWARD with the same SEQ: the second was ACKed as a retry and the chair did not
    move, while the host reported the step done and planned on from the next cell."""
    sim = make_sim(time_scale=50.0)
    for run in (1, 2):
        link = make_link(sim.slave_path, heartbeat=False)  # a fresh link, as a new process
        link.status()  # the CLI reads the status first; the link must not rely on it
        _, st = link.execute("FORWARD", 0.05, 3.0)
        assert st.result == proto.Result.DONE
        assert st.x == pytest.approx(0.05 * run, abs=0.01), f"run {run} did not move"
        link.close()
    fresh = make_link(sim.slave_path, heartbeat=False)  # no status read before the move
    fresh.execute("FORWARD", 0.05, 3.0)
    assert [e.detail for e in sim.events if e.what == "move"] == ["FORWARD"] * 3
    assert sim.status().x == pytest.approx(0.15, abs=0.01)


def test_a_reopened_port_is_not_taken_for_a_retry_of_a_move_another_host_sent(make_sim, make_link):
    """The link re-read the controller's last accepted SEQ only for its first move. Another
    host that drove the controller while the port was away left its own SEQ there, and the
    reopened link's next identical move, when its counter came to that SEQ (1 time in 255),
    was ACKed as a retry and reported DONE without the chair moving."""
    sim = make_sim(time_scale=50.0)
    a = make_link(sim.slave_path, heartbeat=False)
    a.execute("FORWARD", 0.05, 3.0)
    a._drop_port("unplugged")  # as a USB adapter pulled out
    # a second host takes the port meanwhile, once A's reader has let go of its lock (a
    # closed descriptor holds it until a read in progress on it returns)
    deadline = time.monotonic() + 5.0
    while True:
        try:
            b = make_link(sim.slave_path, heartbeat=False)
            break
        except LinkError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.02)
    b._seq = (a._seq + 1) & 0xFF
    seq_b, _ = b.execute("FORWARD", 0.05, 3.0)
    b.close(stop=False)
    assert a.reconnect()
    a._seq = (seq_b - 1) & 0xFF  # A's counter comes round to B's SEQ
    x0 = sim.status().x
    _, st = a.execute("FORWARD", 0.05, 3.0)
    assert st.result == proto.Result.DONE
    assert sim.status().x - x0 == pytest.approx(0.05, abs=0.01), "ACKed as a retry, unmoved"
    assert [e.detail for e in sim.events if e.what == "move"] == ["FORWARD"] * 3


def test_link_settings_it_cannot_run_with_are_refused():
    from wheelgrid_drive.link import check_link_settings

    check_link_settings(115200, 0.1, 3, 0.1, 0.5)
    for kw, message in (
        ({"baud": 0}, "baud must be > 0"),
        ({"baud": 99_999_999_999}, "baud must be <= 12000000"),  # the OS: "signed integer..."
        ({"reply_timeout": float("nan")}, "reply_timeout"),
        ({"reply_timeout": 1e12}, "reply_timeout"),
        ({"retries": -1}, "retries"),
        ({"heartbeat_period": 0.5}, "half the controller's 0.5 s watchdog"),
        ({"reconnect_period": 0.0}, "reconnect_period"),
    ):
        with pytest.raises(ValueError, match=message):
            MotorLink("/dev/null", **kw)  # type: ignore[arg-type]


def test_a_set_pose_the_status_could_not_report_is_refused(make_sim, make_link):
    """A CRC-valid SET_POSE at the edge of int32 mm used to be taken; the next move then
    overflowed the STATUS pose and killed the controller's thread."""
    import struct

    sim = make_sim()
    link = make_link(sim.slave_path, heartbeat=False)
    reply = link.request(proto.MsgType.SET_POSE, struct.pack(">iii", 2_000_000_000, 0, 0))
    assert reply.type == proto.MsgType.NAK and reply.payload[1] == proto.Nak.BAD_POSE
    with pytest.raises(ValueError, match="outside"):
        proto.pack_pose(2_000_000.0, 0.0, 0.0)  # the host refuses to build it at all
    _, st = link.execute("FORWARD", 0.05, 3.0)
    assert st.result == proto.Result.DONE and st.x == pytest.approx(0.05, abs=0.01)


def test_motor_sim_refuses_settings_that_break_it_and_never_deletes_a_file(tmp_path, capsys):
    from wheelgrid_drive.motor_sim import main as sim_main

    precious = tmp_path / "precious.txt"
    precious.write_text("keep me\n")
    assert sim_main(["--link", str(precious)]) == 2
    assert precious.read_text() == "keep me\n" and "not a symlink" in capsys.readouterr().err
    # a link in a folder that is not there is bad input, said as the link's (it was "cannot
    # open a pty", exit 1, the pty left open)
    assert sim_main(["--link", str(tmp_path / "no_such_dir" / "chair.pty")]) == 2
    assert "--link" in (err := capsys.readouterr().err) and "No such file" in err, err
    for flag in ("--heartbeat-timeout", "--x", "--delay"):  # NaN: no watchdog, a dead thread
        assert sim_main([flag, "nan"]) == 2
        assert f"{flag} must be finite" in capsys.readouterr().err
    assert sim_main(["--x", "1e10"]) == 2
    assert "int32 mm" in capsys.readouterr().err
    port = tmp_path / "ttyWG"
    assert sim_main(["--link", str(port), "--pose-log", str(tmp_path / "no" / "log.csv")]) == 1
    assert "cannot open the pose log" in capsys.readouterr().err
    assert not os.path.lexists(port)  # no link left pointing at a closed pty


def test_an_unacknowledged_stop_silences_the_link_so_the_watchdog_stops_the_chair(
    make_sim, make_link, wait
):
    """The heartbeats went on after a STOP that no reply confirmed, feeding the controller's
    watchdog: a chair whose STOP was lost drove on to the end of its cell."""
    sim = make_sim(time_scale=1.0)
    link = make_link(sim.slave_path)
    link.move("FORWARD", 1.2, 3.0)  # 1.4 s of driving
    sim.drop_stop_next = 1 + link.retries  # the STOP and every retry of it are lost
    assert link.stop() is False and link.stop_owed
    assert any("falls silent" in m for k, m in link.events if k == "stop")
    with pytest.raises(LinkError, match="STOP went unacknowledged"):
        link.status()  # nothing that would feed the watchdog goes out
    # the controller's own watchdog ends the move (0.5 s), well before the cell's end
    assert wait(lambda: not sim.status().moving, timeout=1.0)
    assert sim.status().result == proto.Result.WATCHDOG
    # then STOP again, acknowledged: the link speaks again
    assert wait(lambda: not link.stop_owed, timeout=3.0)
    assert link.status().result in (proto.Result.WATCHDOG, proto.Result.STOPPED)


def test_a_move_is_never_retried_on_a_reopened_port(make_sim, make_link, wait, tmp_path):
    """A FORWARD whose port vanished and came back while it waited for its ACK was retried on
    the new connection, after the reconnection's STOP: the chair drove off with no fresh command
    after a link fault. The window is the reader thread reporting the loss (the observer, a
    node's logger, can be slow) while the heartbeat thread reopens the port; the observer here
    holds it open until the reopened controller has had its STOP, so the race is always lost."""
    port = str(tmp_path / "ttyWG")
    sim1 = make_sim(link=port)
    link = make_link(port, reply_timeout=5.0, reconnect_period=0.1)
    sims = []

    def on_event(kind, message):
        link.events.append((kind, message))
        if kind == "vanished" and not sims:
            sims.append(make_sim(link=port))  # the adapter comes back under the same name
            assert wait(lambda: link.stats.reconnects == 1, 10.0)
            assert wait(lambda: any(e.what == "stop" for e in sims[0].events), 10.0)

    link.on_event = on_event
    link.status()  # the move's own first request (it reads the controller's last SEQ) passes
    sim1.drop_move_next = 1  # the FORWARD is lost: its ACK is awaited for reply_timeout
    out = {}

    def drive():
        try:
            out["seq"] = link.move("FORWARD", 1.2, 3.0)
        except LinkError as exc:
            out["error"] = exc

    th = threading.Thread(target=drive)
    th.start()
    assert wait(lambda: sim1.drop_move_next == 0, 10.0)
    sim1.vanish()  # unplugged while the host waits for the FORWARD's ACK
    th.join(30.0)
    assert not th.is_alive()
    sim2 = sims[0]
    assert "error" in out, f"the FORWARD was retried on the reopened port: {moves(sim2)}"
    assert moves(sim1) == [] and moves(sim2) == []
    rx = [e.detail for e in sim2.events if e.what == "rx"]
    assert rx[0] == "STOP" and not set(rx) & set(proto.MOVE_TYPES), rx
    assert not sim2.status().moving


def test_a_plan_is_not_resumed_after_its_link_was_lost_and_reopened(
    make_sim, make_link, wait, tmp_path
):
    """A port lost and reopened between two steps of a plan, with no request in flight: the
    next step's MOVE went out on the reopened port after its STOP, and the chair drove on
    after a link fault with no new command."""
    port = str(tmp_path / "ttyWG")
    sim1 = make_sim(link=port, pose=(0.6, -3.0, YAW["down"]))
    link = make_link(port, reconnect_period=0.1)
    steps = plan_steps((2, 0), ["right"] * 3, "down")
    sims = []

    def on_step(step, record):
        if step is steps[0]:  # the first move done: the adapter is unplugged and comes back
            sim1.vanish()
            assert wait(lambda: link.stats.disconnects == 1, 10.0)
            sims.append(make_sim(link=port, pose=(1.8, -3.0, 0.0)))
            assert wait(lambda: link.stats.reconnects == 1, 10.0)
            assert wait(lambda: any(e.what == "stop" for e in sims[0].events), 10.0)

    result = run_steps(link, steps, distance_m=1.2, speed_kmh=3.0, on_step=on_step)
    assert not result.ok and result.done == 1 and "lost during the plan" in result.error
    assert [d for _, d in moves(sim1)] == ["LEFT_FORWARD"]
    assert moves(sims[0]) == [], "the plan went on on the reopened port"


def test_a_port_lost_mid_move_records_the_move_the_controller_acknowledged(
    make_sim, make_link, wait, tmp_path
):
    """A port lost while a move ran was recorded as FAILED "STATUS_REQ not sent" with no seq:
    the record read as if the step had never started, though the controller had ACKed the
    move and the chair had driven part of it. The record now carries that move's seq."""
    port = str(tmp_path / "ttyWG")
    sim = make_sim(link=port, pose=(0.6, -3.0, YAW["down"]))
    link = make_link(port, reconnect_period=10.0)
    steps = plan_steps((2, 0), ["right"], "down")
    records: list[dict] = []

    def vanish_once_moving() -> None:
        assert wait(lambda: any(e.what == "move" for e in sim.events), 5.0)
        sim.vanish()

    threading.Thread(target=vanish_once_moving, daemon=True).start()
    result = run_steps(
        link, steps, distance_m=1.2, speed_kmh=3.0, on_step=lambda s, r: records.append(r)
    )
    assert not result.ok and result.done == 0
    [(seq, action)] = moves(sim)
    assert action == "LEFT_FORWARD"
    assert records[0]["ack"] == "FAILED" and records[0]["seq"] == seq, records


def test_a_plan_whose_start_checks_saw_the_old_port_does_not_start_on_the_reopened_one(
    make_sim, make_link, wait, tmp_path
):
    """The drive asks the controller (its status, the start pose) before the run, and the run
    took its connection count only as it began: a port lost and reopened in between (well
    under a millisecond, but a real gap) let the first MOVE out on the reopened port. The
    count the caller took before its questions now bounds the run."""
    port = str(tmp_path / "ttyWG")
    sim1 = make_sim(link=port, pose=(0.6, -3.0, YAW["down"]))
    link = make_link(port, reconnect_period=0.1)
    steps = plan_steps((2, 0), ["right"] * 2, "down")
    connection = link.connection
    link.status()  # the start checks, on the port as it was
    sim1.vanish()
    assert wait(lambda: link.stats.disconnects == 1, 10.0)
    sim2 = make_sim(link=port, pose=(0.6, -3.0, YAW["down"]))
    assert wait(lambda: link.stats.reconnects == 1 and not link.stop_owed, 10.0)
    result = run_steps(link, steps, distance_m=1.2, speed_kmh=3.0, connection=connection)
    assert not result.ok and result.done == 0 and "lost during the plan" in result.error
    assert moves(sim2) == [], "the plan started on the reopened port"


def test_a_step_checked_on_the_old_port_is_not_sent_on_one_reopened_after_its_check(
    make_sim, make_link, wait, tmp_path
):
    """run_steps compared the connection count and then called execute(), whose move went out
    on whatever port was open by then: the port lost and reopened in between (the thread
    descheduled there; a review stalled it there to show it) and the next step's MOVE drove
    the chair on the reopened controller, which no check had asked. The count now goes with
    the move, and the link refuses it on a later connection."""
    port = str(tmp_path / "ttyWG")
    sims = [make_sim(link=port, pose=(0.6, -3.0, YAW["down"]))]
    link = make_link(port, reconnect_period=0.1)
    real_execute, calls = link.execute, []

    def stalled_after_the_check(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:  # the second step, its checks passed on the first port
            sims[0].vanish()
            sims.append(make_sim(link=port, pose=(1.8, -3.0, 0.0)))
            assert wait(lambda: link.stats.reconnects == 1 and not link.stop_owed, 10.0)
        return real_execute(*args, **kwargs)

    link.execute = stalled_after_the_check
    steps = plan_steps((2, 0), ["right"] * 3, "down")
    result = run_steps(link, steps, distance_m=1.2, speed_kmh=3.0)
    assert not result.ok and result.done == 1, result
    assert "was lost since the checks" in result.error, result.error
    assert moves(sims[1]) == [], "the plan went on on the reopened port"


def test_a_reopened_port_takes_nothing_before_its_stop(make_sim, make_link, wait, tmp_path):
    """Host duty 5: the first frame on a reopened port is STOP. Another thread's request (a
    plan's status read, a new move) could go out between the reopening and that STOP; here it
    is made from the "reconnected" observer, which runs in exactly that gap."""
    port = str(tmp_path / "ttyWG")
    sim1 = make_sim(link=port)
    link = make_link(port, reconnect_period=0.1)
    refused = []

    def on_event(kind, message):
        link.events.append((kind, message))
        if kind == "reconnected":
            try:
                link.status()
            except LinkError as exc:
                refused.append(str(exc))

    link.on_event = on_event
    sim1.vanish()
    sim2 = make_sim(link=port)
    assert wait(lambda: link.stats.reconnects == 1, 10.0)
    rx = [e.detail for e in sim2.events if e.what == "rx"]
    assert rx and rx[0] == "STOP", rx
    assert refused and "just reopened" in refused[0], refused
    assert link.status().result is not None  # once the STOP is acknowledged, requests go out


def _until_next_seq_is(link, seq):
    """Poll STATUS until the link's next request would carry ``seq`` (the 256-value wrap)."""
    while (link._seq + 1) & 0xFF != seq:
        link.status()


def test_a_refused_move_does_not_hide_the_last_accepted_one_from_the_seq_rule(make_sim, make_link):
    """A NAKed move is not the controller's last move (rule 4 remembers accepted ones). The host
    took the NAKed SEQ for it, so once the accepted move's SEQ came round again, an identical
    move was ACKed as its retry and never driven."""
    sim = make_sim(time_scale=1.0)
    link = make_link(sim.slave_path, heartbeat=False)
    first = link.move("FORWARD", 0.3, 3.0)  # still driving when the next move comes
    with pytest.raises(LinkError, match="BUSY"):
        link.move("LEFT_FORWARD", 0.3, 3.0)
    _until_next_seq_is(link, first)
    seq, st = link.execute("FORWARD", 0.3, 3.0)
    assert seq != first and st.result == proto.Result.DONE
    assert [d for _, d in moves(sim)] == ["FORWARD", "FORWARD"]


def test_a_move_whose_ack_was_lost_is_avoided_by_the_next_moves_seq(make_sim, make_link):
    """A move the controller accepted while every ACK of it was lost is its last move. The host
    kept the move before it as the one to avoid, and a later identical move with the lost one's
    SEQ was answered as its retry: the chair did not move and the step failed."""
    sim = make_sim(time_scale=50.0)
    link = make_link(sim.slave_path, heartbeat=False, retries=1)
    link.execute("FORWARD", 0.05, 3.0)
    sim.drop_tx_next = 2  # the ACK and the retry's ACK
    with pytest.raises(LinkError):
        link.move("FORWARD", 0.05, 3.0)
    lost = sim.status().last_seq
    _until_next_seq_is(link, lost)
    seq, st = link.execute("FORWARD", 0.05, 3.0)
    assert seq != lost and st.result == proto.Result.DONE
    assert [d for _, d in moves(sim)] == ["FORWARD"] * 3


def test_an_e_stop_before_the_move_reaches_the_wire_keeps_it_off_the_wire(make_sim, make_link):
    """The runner checks its abort flag, then the link reads STATUS and writes the move. An
    e-stop in between (its flag set, its STOP acknowledged) was followed by the move itself:
    the chair set off for one round trip before the move's own abort check stopped it. The
    move is now refused at the wire, under the lock the e-stop's STOP is written with."""
    sim = make_sim(time_scale=1.0)
    link = make_link(sim.slave_path, heartbeat=False)
    abort = threading.Event()
    real_status = link.status

    def e_stop_meanwhile(connection: int | None = None) -> proto.Status:
        st = real_status(connection)
        abort.set()  # as the drive node's e-stop: the flag, then the STOP
        assert link.stop()
        return st

    link.status = e_stop_meanwhile
    with pytest.raises(LinkAbortedError, match="not sent"):
        link.execute("FORWARD", 1.2, 3.0, abort=abort)
    assert moves(sim) == []  # the controller never took it
    assert sim.state == proto.State.IDLE


def test_the_simulator_keeps_only_its_newest_events(make_sim, monkeypatch):
    """Every frame the simulator received (each heartbeat) was kept for ever, ~5 MB an hour
    for a simulator left running (a review): it keeps between MAX_EVENTS and twice as many,
    the newest."""
    from wheelgrid_drive import motor_sim

    monkeypatch.setattr(motor_sim, "MAX_EVENTS", 5)
    sim = make_sim()
    for i in range(40):
        sim._event("test", seq=i)
    ours = [e.seq for e in sim.events if e.what == "test"]
    assert len(sim.events) <= 10 and ours and ours[-1] == 39
    assert ours == list(range(ours[0], 40))  # the newest, in order
