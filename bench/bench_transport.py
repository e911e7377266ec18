"""Benchmark: whole iPhone clouds from one process to another over DDS on this machine.

    python bench/bench_transport.py [--quick] [--json FILE]

A publisher process sends organised 256 x 192 PointCloud2 frames (x, y, z, confidence: 786 kB,
the size the bridge and an imported Stray bag publish) on sensor-data QoS (best effort) at
10 and 30 Hz; a subscriber process counts what arrives and when. Figure: the share delivered
and the publish -> callback latency with wheelgrid's Fast DDS profile
(wheelgrid_common/fastdds_loopback.xml: 16 MB shared-memory segment, UDP on 127.0.0.1), which
every wheelgrid process starts with; baseline, run beside it: the same with Fast DDS's default
transports (``WHEELGRID_FASTDDS_PROFILE=0``: a 512 kB segment, larger samples as UDP fragments).
Where this process may open a raw socket (root), it also counts RTPS packets leaving on any
interface but loopback during the runs: it must be 0 (discovery stays on this machine).
"""

from __future__ import annotations

import argparse
import array
import json
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from wheelgrid_common.ros_env import child_env, configure_ros_env

WIDTH, HEIGHT = 256, 192
TOPIC = "/bench_transport/points"


def publisher(rate: float, count: int) -> int:
    import numpy as np
    import rclpy
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2, PointField

    from wheelgrid_common.qos import SENSOR_QOS

    configure_ros_env()  # the profile, unless WHEELGRID_FASTDDS_PROFILE=0
    rclpy.init()
    node = Node("bench_transport_pub")
    pub = node.create_publisher(PointCloud2, TOPIC, SENSOR_QOS)
    msg = PointCloud2(height=HEIGHT, width=WIDTH, point_step=16, row_step=16 * WIDTH)
    msg.fields = [
        PointField(name=k, offset=4 * i, datatype=PointField.FLOAT32, count=1)
        for i, k in enumerate("xyzc")
    ]
    msg.is_dense = False
    rng = np.random.default_rng(0)
    msg.data = array.array("B", rng.random(WIDTH * HEIGHT * 4, dtype=np.float32).tobytes())
    deadline = time.monotonic() + 30.0
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)  # the match settles both ways
    t0 = time.monotonic()
    for i in range(count):
        slot = t0 + i / rate
        time.sleep(max(0.0, slot - time.monotonic()))
        msg.header.frame_id = f"{i} {time.time():.6f}"  # the wall clock both processes share
        pub.publish(msg)
    time.sleep(1.0)
    node.destroy_node()
    rclpy.shutdown()
    return 0


def subscriber(seconds: float) -> int:
    import rclpy
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2

    from wheelgrid_common.qos import SENSOR_QOS

    configure_ros_env()
    rclpy.init()
    node = Node("bench_transport_sub")
    got: list[tuple[int, float]] = []

    def on_cloud(m: PointCloud2) -> None:
        seq, sent = m.header.frame_id.split()
        got.append((int(seq), time.time() - float(sent)))

    node.create_subscription(PointCloud2, TOPIC, on_cloud, SENSOR_QOS)
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    import os

    seqs, lats = [s for s, _ in got], [lat for _, lat in got]
    profile = os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE", "")
    print(json.dumps({"seqs": seqs, "lat": lats, "profile": profile}))
    node.destroy_node()
    rclpy.shutdown()
    return 0


class RtpsCounter:
    """RTPS packets leaving on any interface but loopback (AF_PACKET: root only)."""

    def __init__(self) -> None:
        self.count = 0
        self.sock: socket.socket | None = None
        try:
            self.sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.ntohs(3))
            self.sock.settimeout(0.2)
        except (AttributeError, OSError):
            self.sock = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> RtpsCounter:
        if self.sock is not None:
            self._thread.start()
        return self

    def _run(self) -> None:
        assert self.sock is not None
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            if addr[0] != "lo" and b"RTPS" in data:
                self.count += 1

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self.sock is not None:
            self._thread.join(2.0)
            self.sock.close()


def run(rate: float, count: int, profile: bool) -> dict[str, float]:
    env = child_env()
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)  # each child chooses for itself
    if not profile:
        env["WHEELGRID_FASTDDS_PROFILE"] = "0"
    me = [sys.executable, str(Path(__file__).resolve())]
    seconds = count / rate + 8.0
    sub = subprocess.Popen(
        [*me, "--role", "sub", "--seconds", str(seconds)],
        env=env,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        pub = subprocess.run(
            [*me, "--role", "pub", "--rate", str(rate), "--count", str(count)],
            env=env,
            timeout=seconds + 60,
            check=True,
        )
        del pub
        out, _ = sub.communicate(timeout=seconds + 60)
    finally:
        if sub.poll() is None:
            sub.kill()
            sub.wait()
    got = json.loads(out.strip().splitlines()[-1])
    lat = got["lat"] or [float("nan")]
    if bool(got["profile"]) != profile:
        raise RuntimeError(f"the subscriber ran with profile {got['profile']!r}, not {profile}")
    return {
        "delivered": 100.0 * len(set(got["seqs"])) / count,
        "p50_ms": 1000.0 * statistics.median(lat),
        "max_ms": 1000.0 * max(lat),
    }


def row_line(r: dict[str, Any]) -> str:
    """One result as a line: the value with its unit, the baseline (where there is one) in the
    same unit, then the note."""
    value = f"{r['value']} {r['unit']}".rstrip()
    baseline = f" (baseline {r['baseline']} {r['unit']})" if r["baseline"] != "" else ""
    return f"{r['figure']}: {value}{baseline}; {r['note']}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames")
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument("--role", choices=("pub", "sub"), help=argparse.SUPPRESS)
    ap.add_argument("--rate", type=float, default=10.0, help=argparse.SUPPRESS)
    ap.add_argument("--count", type=int, default=100, help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, default=20.0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role == "pub":
        return publisher(args.rate, args.count)
    if args.role == "sub":
        return subscriber(args.seconds)

    rows = []
    with RtpsCounter() as leaks:
        for rate, seconds in ((10.0, 10.0), (30.0, 10.0)):
            count = int(rate * (3.0 if args.quick else seconds))
            ours = run(rate, count, profile=True)
            base = run(rate, count, profile=False)
            print(f"{rate:g} Hz, {count} clouds: profile {ours}, Fast DDS defaults {base}")
            rows.append(
                dict(
                    figure=f"786 kB clouds delivered across processes at {rate:g} Hz",
                    value=round(ours["delivered"], 1),
                    unit="%",
                    baseline=round(base["delivered"], 1),
                    ratio=ours["delivered"] / max(base["delivered"], 1e-9),
                    note=f"n={count}, best effort; latency p50 {ours['p50_ms']:.1f} ms, max "
                    f"{ours['max_ms']:.1f} ms (defaults {base['p50_ms']:.1f} / "
                    f"{base['max_ms']:.1f} ms); baseline: Fast DDS default transports",
                )
            )
    counted = leaks.sock is not None
    rows.append(
        dict(
            figure="RTPS packets leaving the machine during these runs",
            value=leaks.count if counted else "not counted (no raw socket: not root)",
            unit="packets" if counted else "",
            baseline="",
            ratio="",
            note="must be 0: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, UDP on 127.0.0.1",
        )
    )
    for r in rows:
        print(row_line(r))
    if args.json:
        args.json.write_text(json.dumps({"rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
