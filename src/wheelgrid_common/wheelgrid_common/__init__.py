"""Shared, ROS-light helpers: PointCloud2 <-> numpy, QoS profiles, ROS environment, file formats (PLY, TUM, map_server)."""
