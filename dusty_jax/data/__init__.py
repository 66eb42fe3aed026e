"""Data: real-scan readers (kitti, mpo), synthetic scenes, prepared arrays."""
