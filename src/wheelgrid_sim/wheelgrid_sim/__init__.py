"""Synthetic iPhone-LiDAR room simulator with exact ground truth, written as rosbag2 bags."""
