"""Benchmark: Stray capture -> stream-stray -> TCP -> iphone_bridge -> DDS -> subscriber.

Plays the real iPhone capture (../shared/data/stray-iphone-room, 942 frames, 15.7 s) at 1x real
time into an ``iphone_bridge`` process and counts frames sent (TCP), published (the bridge's
/iphone/bridge_status) and received (a subscriber in this process) on every bridge topic, with
the bridge's CPU use and the bridge-receive -> subscriber latency of /iphone/points.

Baseline (same process, same frames): the bridge with Fast DDS's default transports
(``WHEELGRID_FASTDDS_PROFILE=0``), i.e. without the large shared-memory profile every wheelgrid
process applies by default (wheelgrid_common/fastdds_loopback.xml). Ratio = figure / baseline.

    python bench/bench_bridge.py [--quick] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from wheelgrid_common.ros_env import child_env, configure_ros_env
from wheelgrid_common.testing import (
    diagnostics_log,
    free_port,
    managed_process,
    python_module,
    rclpy_context,
    shared_data,
    spin_until,
)

TOPICS = [
    "/iphone/points",
    "/iphone/odometry",
    "/iphone/depth/image",
    "/iphone/depth/camera_info",
    "/iphone/confidence/image",
]


def _capture() -> Path:
    return shared_data("stray-iphone-room", Path(__file__).resolve().parents[1])


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run(indices: range, profile: bool) -> dict[str, float]:
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2

    from wheelgrid_common.qos import SENSOR_QOS
    from wheelgrid_mapping.cli_stray import stream_export
    from wheelgrid_mapping.stray import StrayExport

    exp = StrayExport(_capture())
    port = free_port()
    env = child_env()
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    if not profile:
        env["WHEELGRID_FASTDDS_PROFILE"] = "0"
    cmd = python_module(
        "wheelgrid_mapping.iphone_bridge_node",
        "--ros-args",
        "-p",
        f"port:={port}",
        "-p",
        "stamp_mode:=receive",
    )
    types = [PointCloud2, Odometry, Image, CameraInfo, Image]
    with managed_process(cmd, env=env) as proc, rclpy_context() as ctx:
        import rclpy

        node = rclpy.create_node("bench_bridge_sub", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        counts = dict.fromkeys(TOPICS, 0)
        latency: list[float] = []

        def on_msg(topic: str, msg: Any) -> None:
            counts[topic] += 1
            if topic == "/iphone/points":
                st = msg.header.stamp
                latency.append(time.time() - (st.sec + 1e-9 * st.nanosec))

        for topic, typ in zip(TOPICS, types, strict=True):
            node.create_subscription(typ, topic, lambda m, t=topic: on_msg(t, m), SENSOR_QOS)
        status = diagnostics_log(node, "/iphone/bridge_status")
        if not spin_until(
            ex, lambda: all(node.count_publishers(t) == 1 for t in TOPICS) and bool(status), 30
        ):
            raise RuntimeError("bridge did not come up")
        out: dict[str, Any] = {}
        cpu0 = _cpu_s(proc.pid)

        def send() -> None:
            out["stats"] = stream_export(exp, "127.0.0.1", port, rate=1.0, indices=indices)

        th = threading.Thread(target=send)
        th.start()
        spin_until(ex, lambda: not th.is_alive(), len(indices) / 60 * 3 + 30)
        th.join()
        n = out["stats"].frames_sent
        spin_until(ex, lambda: min(counts.values()) >= n, 3.0)  # let the last frames land
        spin_until(ex, lambda: status[-1].get("frames_published") == str(n), 3.0)
        cpu = _cpu_s(proc.pid) - cpu0
        node.destroy_node()
        ex.shutdown()
    st = out["stats"]
    lat = np.array(latency) * 1000 if latency else np.array([np.nan])
    return {
        "frames_sent": float(n),
        "frames_published": float(status[-1].get("frames_published", "nan")),
        "clouds_received": float(counts["/iphone/points"]),
        "odometry_received": float(counts["/iphone/odometry"]),
        "images_received_min": float(min(counts[t] for t in TOPICS[2:])),
        "cloud_loss_pct": 100.0 * (1 - counts["/iphone/points"] / max(n, 1)),
        "cloud_latency_p50_ms": float(np.median(lat)),
        "cloud_latency_p95_ms": float(np.percentile(lat, 95)),
        "bridge_cpu_pct_of_one_core": 100.0 * cpu / max(st.wall_s, 1e-9),
        "sender_max_lag_ms": 1000.0 * st.max_lag_s,
        "stream_wall_s": st.wall_s,
        "capture_s": st.capture_s,
    }


UNITS = {
    "frames_sent": "frames",
    "frames_published": "frames",
    "clouds_received": "frames",
    "odometry_received": "frames",
    "images_received_min": "frames",
    "cloud_loss_pct": "%",
    "cloud_latency_p50_ms": "ms",
    "cloud_latency_p95_ms": "ms",
    "bridge_cpu_pct_of_one_core": "%",
    "sender_max_lag_ms": "ms",
    "stream_wall_s": "s",
    "capture_s": "s",
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="120 frames (2 s) instead of all")
    ap.add_argument("--json", type=Path, help="write {'rows': [...]} here")
    args = ap.parse_args(argv)
    configure_ros_env()
    if not (_capture() / "depth").is_dir():
        print(f"bench_bridge: {_capture()} not present", file=sys.stderr)
        return 2
    from wheelgrid_mapping.stray import StrayExport

    total = len(StrayExport(_capture()))
    indices = range(300, 420) if args.quick else range(total)
    print(f"bench_bridge: {len(indices)} frames at 1x real time, 2 runs", flush=True)
    res = run(indices, profile=True)
    base = run(indices, profile=False)
    rows = []
    print(f"{'figure':30s} {'value':>10s} {'baseline':>10s} {'ratio':>7s}  unit")
    for k, v in res.items():
        b = base[k]
        ratio = v / b if b not in (0.0,) and np.isfinite(b) else float("nan")
        rows.append({"figure": k, "value": v, "unit": UNITS[k], "baseline": b, "ratio": ratio})
        print(f"{k:30s} {v:10.2f} {b:10.2f} {ratio:7.2f}  {UNITS[k]}")
    print("baseline = the same run with Fast DDS default transports (WHEELGRID_FASTDDS_PROFILE=0)")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
