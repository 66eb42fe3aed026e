"""Data: point cloud files of any sensor (points: read_points, write_points;
ouster: Ouster recordings), recordings of many sweeps (recordings:
read_sweeps: ROS bags), readers of the paper's datasets (kitti, mpo) and
the peers' (kitti360, nuscenes), point cloud unfolding (unfolding:
to_range_image), sensor specs estimated from sweeps (estimate), the
simulator (scene, simulated_lidar, synthetic), preparing and reading
prepared arrays (prepare, arrays), training batches (pipeline), and scans
given as files (scan_files).

The names below are importable from here, loaded on first use (the
unfolding imports JAX through the codec)."""

import importlib

_EXPORTS = {
    'read_points': 'dusty_jax.data.points',
    'ring_field': 'dusty_jax.data.points',
    'write_points': 'dusty_jax.data.points',
    'read_sweeps': 'dusty_jax.data.recordings',
    'to_range_image': 'dusty_jax.data.unfolding',
    'unfold': 'dusty_jax.data.unfolding',
    'estimate_sensor': 'dusty_jax.data.estimate',
}


def __getattr__(name):
  if name in _EXPORTS:
    module = importlib.import_module(_EXPORTS[name])
    return getattr(module, 'estimate' if name == 'estimate_sensor' else name)
  raise AttributeError(f'module {__name__!r} has no attribute {name!r}')


def __dir__():
  return sorted(list(globals()) + list(_EXPORTS))
