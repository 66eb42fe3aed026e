"""KITTI odometry velodyne scans (HDL-64E), read and unfolded in firing order."""

from __future__ import annotations

import os

import numpy as np

from dusty_jax.data import unfolding
from dusty_jax.sensor import SensorSpec

# Sequences per split, as in the paper and the authors' code.
SPLITS = {
    'train': (0, 1, 2, 3, 4, 5, 6, 7, 9, 10),
    'val': (8,),
    'test': tuple(range(11, 22)),
}

POINT_BYTES = 16  # float32 x, y, z, reflectance.


def read_bin(path: str) -> np.ndarray:
  """Reads a velodyne ``.bin`` into an (N, 4) float32 array, checking it."""
  try:
    size = os.path.getsize(path)
  except OSError as e:
    raise ValueError(f'{path}: cannot read ({e.strerror})') from None
  if size == 0:
    raise ValueError(f'{path}: empty file')
  if size % POINT_BYTES:
    raise ValueError(f'{path}: size {size} bytes is not a multiple of '
                     f'{POINT_BYTES} (float32 x, y, z, reflectance per point); '
                     'truncated or not a KITTI velodyne file')
  points = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
  unfolding.check_points(points, path, finite=True)
  return points


def write_bin(path: str, points: np.ndarray):
  """Writes (N, 3 or 4) points as a KITTI ``.bin`` (reflectance 0 if absent)."""
  points = np.asarray(points, np.float32)
  if points.shape[1] == 3:
    points = np.concatenate([points, np.zeros((len(points), 1), np.float32)], 1)
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  points[:, :4].tofile(path)


def list_split(root: str, split: str) -> list[str]:
  """Sorted ``.bin`` paths of a split under ``root/sequences/NN/velodyne``."""
  if split not in SPLITS:
    raise ValueError(f'unknown KITTI split {split!r}; known: {sorted(SPLITS)}')
  seq_root = os.path.join(root, 'sequences')
  if not os.path.isdir(seq_root):
    raise FileNotFoundError(
        f'{seq_root}: no such directory; expected the KITTI odometry layout '
        'ROOT/sequences/NN/velodyne/*.bin')
  paths = []
  for seq in SPLITS[split]:
    d = os.path.join(seq_root, f'{seq:02d}', 'velodyne')
    if os.path.isdir(d):
      paths += sorted(os.path.join(d, f) for f in os.listdir(d)
                      if f.endswith('.bin'))
  return paths


def load_scan(path: str, sensor: SensorSpec, return_xyz: bool = False):
  """Reads and unfolds one scan, its rows from the firing order (the
  authors' rule): (H, W) depth[, (H, W, 3) xyz], :class:`unfolding.Unfolded`."""
  u = unfolding.unfold(read_bin(path), sensor, source=path, firing_order=True)
  return (u.depth, u.xyz, u) if return_xyz else (u.depth, u)
