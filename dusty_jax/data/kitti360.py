"""KITTI-360 velodyne sweeps (HDL-64E), split by drive as the peers split them.

Layout, as distributed: ``ROOT/data_3d_raw/2013_05_28_drive_NNNN_sync/
velodyne_points/data/*.bin`` (ROOT may also be data_3d_raw itself). Each
file is float32 x, y, z, reflectance in sensor order, as KITTI odometry's:
read and unfolded as kitti.py does.

The split is LiDARGen's, which R2DM trains and tests on (kazuto1011/r2dm,
data/kitti_360/kitti_360.py, its 'lidargen' split): drives 3, 4, 5, 6, 7, 9
and 10 for training, 0 and 2 for testing, no validation drive. LiDM
(hancyran/LiDAR-Diffusion, lidm/data/kitti.py) splits otherwise: it
validates on drive 3 and trains on the rest; prepare such a split with
``--dataset files`` and split lists. Both train at 64 x 1024 (R2DM's
default builder, LiDM's KITTI-360 configs): the hdl64e preset.
"""

from __future__ import annotations

import glob
import os

from dusty_jax.data import kitti

SPLITS = {
    'train': (3, 4, 5, 6, 7, 9, 10),
    'val': (),
    'test': (0, 2),
}
SENSOR = 'hdl64e'  # 64 x 1024
RAW = 'data_3d_raw'
DRIVE = '*_drive_{:04d}_sync'  # a drive's folder, its date first
ANY_DRIVE = '*_drive_*_sync'
SWEEPS = os.path.join('velodyne_points', 'data', '*.bin')

load_scan = kitti.load_scan


def list_split(root: str, split: str) -> list[str]:
  """Sorted ``.bin`` paths of a split's drives under ``root`` (module docstring)."""
  if split not in SPLITS:
    raise ValueError(f'unknown KITTI-360 split {split!r}; known: {sorted(SPLITS)}')
  raw = os.path.join(root, RAW)
  if not os.path.isdir(raw):
    if not glob.glob(os.path.join(glob.escape(root), ANY_DRIVE)):
      raise FileNotFoundError(
          f'{raw}: no such directory; expected the KITTI-360 layout '
          f'ROOT/{RAW}/2013_05_28_drive_NNNN_sync/{SWEEPS}')
    raw = root
  paths = []
  for drive in SPLITS[split]:
    paths += sorted(glob.glob(os.path.join(glob.escape(raw), DRIVE.format(drive), SWEEPS)))
  return paths
