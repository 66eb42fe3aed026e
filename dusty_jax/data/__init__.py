"""Data: real-scan readers (kitti, mpo), point cloud files of any sensor
(points: read_points, write_points; ouster: Ouster recordings), point cloud
unfolding, the simulator (scene, simulated_lidar, synthetic), preparing and
reading prepared arrays (prepare, arrays), training batches (pipeline), and
scans given as files (scan_files)."""

from dusty_jax.data.points import read_points, ring_field, write_points
