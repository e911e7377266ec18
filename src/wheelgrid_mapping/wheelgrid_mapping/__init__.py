"""Filters and registers iPhone-LiDAR PointCloud2 frames (KISS-ICP) into a levelled 3D map; the iPhone bridge."""
