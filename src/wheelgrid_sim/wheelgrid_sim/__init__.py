"""wheelgrid_sim: a synthetic iPhone-LiDAR room scanner with exact ground truth.

Public API (others code against these names):
  scene:      Box, Scene, paper_scene(), random_scene(seed); Scene.expected_grid(...),
              Scene.sample_surface_points(spacing)
  camera:     DepthCamera(...).intrinsics()/.render(...), depth_to_points(depth, K), raycast
  trajectory: make_trajectory(scene, frames, rate, seed) -> (stamps, room_from_optical poses)
  odometry:   arkit_like_odometry(poses_room, seed) -> (odom_from_optical poses, odom_from_room)
  simulate:   simulate(out_dir, *, seed, frames, rate, scene, stride, storage) -> SimResult,
              load_ground_truth(out_dir) -> GroundTruth
"""

from wheelgrid_sim.camera import DepthCamera, depth_to_points, raycast
from wheelgrid_sim.odometry import arkit_like_odometry
from wheelgrid_sim.scene import Box, Scene, paper_scene, random_scene
from wheelgrid_sim.simulate import (
    FRAME_ID,
    ODOM_TOPIC,
    TOPIC,
    GroundTruth,
    SimResult,
    load_ground_truth,
    map_from_room,
    simulate,
)
from wheelgrid_sim.trajectory import camera_pose, make_trajectory

__all__ = [
    "FRAME_ID",
    "ODOM_TOPIC",
    "TOPIC",
    "Box",
    "DepthCamera",
    "GroundTruth",
    "Scene",
    "SimResult",
    "arkit_like_odometry",
    "camera_pose",
    "depth_to_points",
    "load_ground_truth",
    "make_trajectory",
    "map_from_room",
    "paper_scene",
    "random_scene",
    "raycast",
    "simulate",
]
