"""Data: real-scan readers (kitti, mpo), point cloud unfolding, the simulator
(scene, simulated_lidar, synthetic), preparing and reading prepared arrays
(prepare, arrays), training batches (pipeline), and scans given as files
(scan_files)."""
