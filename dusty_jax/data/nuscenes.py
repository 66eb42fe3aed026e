"""nuScenes LIDAR_TOP sweeps (Velodyne HDL-32E, 20 Hz), split by the
dataset's versions as the peers split them.

Layout, as distributed: ``ROOT/VERSION/sample_data.json``, the table of
every file a version holds (VERSION: v1.0-trainval, v1.0-test, v1.0-mini),
and the files it names under ROOT: ``samples/LIDAR_TOP/*.pcd.bin`` (the key
frames, 2 Hz) and ``sweeps/LIDAR_TOP/*.pcd.bin`` (the sweeps between them).
Each is float32 x, y, z, intensity, ring (points.read_points); rows come
from the ring field.

The split is RangeLDM's (WoodwindHu/RangeLDM, ldm/nuscenes_range_image.py),
the one peer whose nuScenes loader is published (LiDM's nuScenes config,
hancyran/LiDAR-Diffusion models/baseline/nuscenes/template/config.yaml,
names a loader its repository does not hold): the LIDAR_TOP sweeps between
key frames that v1.0-trainval's table lists for training, those of
v1.0-test's for testing, no validation split (the official train/val split
of trainval's scenes is nuscenes-devkit's, not in the tables). A tree with
v1.0-mini and no v1.0-trainval (the sample download: 10 of trainval's
scenes) trains on the mini's. Both peers train at 32 x 1024: the hdl32e
preset.
"""

from __future__ import annotations

import json
import os

from dusty_jax.data import points, unfolding
from dusty_jax.errors import DataError
from dusty_jax.sensor import SensorSpec

# The versions whose table lists a split's sweeps; the first one present.
SPLITS = {
    'train': ('v1.0-trainval', 'v1.0-mini'),
    'val': (),
    'test': ('v1.0-test',),
}
VERSIONS = ('v1.0-trainval', 'v1.0-test', 'v1.0-mini')
TABLE = 'sample_data.json'
SWEEPS = 'sweeps/LIDAR_TOP/'  # the table's file names of the sweeps kept
SENSOR = 'hdl32e'  # 32 x 1024


def _read_table(path: str) -> list[str]:
  """The file names a sample_data table lists."""
  try:
    with open(path, 'rb') as f:
      records = json.load(f)
  except (OSError, ValueError) as e:
    raise DataError(f'{path}: not a readable nuScenes table ({" ".join(str(e).split())})') \
        from None
  if not isinstance(records, list) or not all(
      isinstance(r, dict) and isinstance(r.get('filename'), str) for r in records):
    raise DataError(f'{path}: not a nuScenes sample_data table (a list of records, each '
                    'with a filename)')
  return [r['filename'] for r in records]


def list_split(root: str, split: str) -> list[str]:
  """Sorted paths of a split's LIDAR_TOP sweeps under ``root`` (module
  docstring); DataError where the table names a file that is not there."""
  if split not in SPLITS:
    raise ValueError(f'unknown nuScenes split {split!r}; known: {sorted(SPLITS)}')
  present = [v for v in VERSIONS if os.path.isfile(os.path.join(root, v, TABLE))]
  if not present:
    raise FileNotFoundError(
        f'{root}: no {TABLE} in any of {", ".join(VERSIONS)}; expected the nuScenes layout '
        f'ROOT/VERSION/{TABLE} and ROOT/{SWEEPS}*.pcd.bin')
  version = next((v for v in SPLITS[split] if v in present), None)
  if version is None:
    return []
  table = os.path.join(root, version, TABLE)
  paths = [os.path.join(root, name)
           for name in sorted(n for n in _read_table(table) if n.startswith(SWEEPS))]
  missing = [p for p in paths if not os.path.isfile(p)]
  if missing:
    raise DataError(f'{table}: {len(missing)} of its {len(paths)} LIDAR_TOP sweeps are not '
                    f'under {root}, e.g. {missing[0]}; download every part of {version}, or '
                    'prepare the files there are with --dataset files')
  return paths


def load_scan(path: str, sensor: SensorSpec, return_xyz: bool = False):
  """(H, W) depth[, (H, W, 3) xyz], :class:`unfolding.Unfolded` of a sweep,
  its rows from its ring field."""
  fields = points.read_points(path)
  u = unfolding.unfold(fields, sensor, ring=points.ring_field(fields, path), source=path)
  return (u.depth, u.xyz, u) if return_xyz else (u.depth, u)
