"""Live iPhone path end to end over DDS on loopback, on the REAL capture in ../shared/data:
`stream-stray` (standing in for the phone) -> iphone_bridge -> mapper (ARKit pose prior) -> map,
compared with the map fused from ARKit's own poses. No frame may be lost at 1x real time."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_stream_stray_bridge_mapper_agrees_with_arkit(repo_root, tmp_path, stray_capture):
    import open3d as o3d

    from wheelgrid_bringup.chain import Monitor
    from wheelgrid_bringup.supervisor import Supervisor, node_argv
    from wheelgrid_common.fileio import read_ply, read_tum
    from wheelgrid_common.ros_env import child_env
    from wheelgrid_common.testing import free_port, rclpy_context
    from wheelgrid_mapping.cli_stray import stream_export
    from wheelgrid_mapping.depth import arkit_pose_to_ros, depth_to_points
    from wheelgrid_mapping.stray import StrayExport

    exp = StrayExport(stray_capture)
    start, n = 300, 120  # 2 s of the capture at 60 fps
    port = free_port()
    sup = Supervisor(tmp_path / "logs", child_env())
    with rclpy_context() as ctx:
        monitor = Monitor(ctx, "iphone_e2e")
        try:
            sup.start("iphone_bridge", node_argv("iphone_bridge", None, {"port": port}))
            sup.start(
                "mapper",
                node_argv(
                    "mapper",
                    None,
                    {
                        "pose_prior_topic": "/iphone/odometry",
                        "max_queue": 1000,
                        "output_dir": str(tmp_path / "map"),
                        "publish_period": 1.0,
                    },
                ),
            )
            _wait(lambda: monitor.node.count_publishers("/iphone/points") == 1, 30, sup)
            _wait(lambda: monitor.node.count_subscribers("/iphone/points") >= 1, 30, sup)
            time.sleep(1.0)  # let the bridge's and the mapper's endpoints finish matching
            stats: dict = {}
            th = threading.Thread(
                target=lambda: stats.update(
                    s=stream_export(
                        exp, "127.0.0.1", port, rate=1.0, indices=range(start, start + n)
                    )
                )
            )
            th.start()
            th.join(timeout=60)
            assert stats["s"].frames_sent == n

            def settled() -> bool:
                m = dict(monitor.state.mapper)
                done = sum(
                    int(m.get(k, 0)) for k in ("frames_used", "frames_failed", "frames_empty")
                )
                return int(m.get("frames_received", 0)) >= n and done >= n

            _wait(settled, 120, sup)
            m = dict(monitor.state.mapper)
            assert int(m["frames_received"]) == n  # no frame lost at 1x real time
            assert int(m["frames_skipped_busy"]) == 0
            ok, msg = monitor.call_trigger("/mapper/save_map", timeout=30)
            assert ok, msg
        finally:
            sup.stop_all()
            monitor.close()

    mapped = read_ply(tmp_path / "map" / "map.ply")
    stamps, poses_map = read_tum(tmp_path / "map" / "trajectory.tum")
    print(f"iPhone live: {n} frames streamed, {n} received, {len(stamps)} registered")
    assert len(stamps) >= 0.75 * n  # the rest refused by failure detection, and counted
    # ARKit's own map: every frame fused with its ARKit pose (ROS z-up odom frame)
    ref = []
    capture = np.array([exp.stamp(i) for i in range(start, start + n)])
    for i in range(start, start + n):
        f = exp.frame(i)
        pts = depth_to_points(f.depth, f.K, f.confidence, min_confidence=1)
        pts = pts[np.isfinite(pts).all(axis=1)].astype(np.float64)
        T = arkit_pose_to_ros(f.pose)
        ref.append(pts @ T[:3, :3].T + T[:3, 3])
    ref_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.vstack(ref)))
    ref_cloud = ref_cloud.voxel_down_sample(0.02)
    # the first registered frame ties the two frames together (map <- odom)
    import json

    report = json.loads((tmp_path / "map" / "report.json").read_text())
    assert all(f["frame"] != 0 for f in report["failures"])  # frame `start` opened the map
    np.testing.assert_allclose(stamps[1] - stamps[0], capture[1] - capture[0], atol=1e-3)
    T_odom0 = arkit_pose_to_ros(exp.frame(start).pose)
    T = poses_map[0] @ np.linalg.inv(T_odom0)
    ref_map = np.asarray(ref_cloud.points) @ T[:3, :3].T + T[:3, 3]
    tree = o3d.geometry.KDTreeFlann(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(ref_map)))
    dist = np.array([np.sqrt(tree.search_knn_vector_3d(p, 1)[2][0]) for p in mapped[::5]])
    within = float((dist < 0.05).mean())
    print(f"iPhone live map vs ARKit-fused map: {100 * within:.1f} % of points within 5 cm")
    assert within >= 0.8


def _wait(pred, timeout: float, sup) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        dead = sup.dead()
        assert not dead, f"node died: {dead}: {sup.tail(dead[0][0])}"
        if pred():
            return
        time.sleep(0.1)
    assert pred(), "timed out"
