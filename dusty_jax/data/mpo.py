"""MPO sparse scans (HDL-32E) with laser ring ids.

Layout, as distributed and read by the authors: ``ROOT/Data/`` holding
``class{C}_set{SSS}_scan{NNNNN}.npy``. Each file is either

  * (N, >=4) points: x, y, z[, ...], ring id in the last column (ring 0 the
    lowest beam, the Velodyne driver's convention; unfold orders the rings
    by their measured elevation, whatever their numbering); or
  * an (H, W', >=3) grid of points already arranged by ring and azimuth
    (W' a multiple of the sensor's width; zeros where there is no return).
"""

from __future__ import annotations

import os
import re

import numpy as np

from dusty_jax.data import unfolding
from dusty_jax.sensor import SensorSpec

SPLITS = {
    'train': (0, 1, 2, 3, 4, 5, 6),
    'val': (7,),
    'test': (8, 9, 10),
}

_NAME = re.compile(r'class\d+_set(\d+)_scan\d+\.npy$')


def list_split(root: str, split: str) -> list[str]:
  if split not in SPLITS:
    raise ValueError(f'unknown MPO split {split!r}; known: {sorted(SPLITS)}')
  data = os.path.join(root, 'Data')
  if not os.path.isdir(data):
    raise FileNotFoundError(
        f'{data}: no such directory; expected the MPO sparse layout '
        'ROOT/Data/class*_set*_scan*.npy')
  sets = set(SPLITS[split])
  out = []
  for f in sorted(os.listdir(data)):
    m = _NAME.match(f)
    if m and int(m.group(1)) in sets:
      out.append(os.path.join(data, f))
  return out


def read_npy(path: str) -> np.ndarray:
  try:
    arr = np.load(path, allow_pickle=False)
  except (OSError, ValueError) as e:
    raise ValueError(f'{path}: not a readable .npy file ({e})') from None
  if arr.size == 0:
    raise ValueError(f'{path}: empty array')
  return arr


def load_scan(path: str, sensor: SensorSpec, return_xyz: bool = False):
  """(H, W) depth[, (H, W, 3) xyz], :class:`unfolding.Unfolded` of one MPO
  file: points unfolded with their ring ids (rows by each ring's elevation),
  or a grid, which is already the image (its kept columns; no Unfolded)."""
  arr = read_npy(path)
  if arr.ndim == 2:
    if arr.shape[1] < 4:
      raise ValueError(f'{path}: point array needs x, y, z and a ring id '
                       f'column, got shape {arr.shape}')
    u = unfolding.unfold(arr[:, :3], sensor, ring=arr[:, -1], source=path)
    return (u.depth, u.xyz, u) if return_xyz else (u.depth, u)
  if arr.ndim == 3:
    h, w, c = arr.shape
    if h != sensor.height or w % sensor.width or c < 3:
      raise ValueError(f'{path}: grid of shape {arr.shape} does not fit sensor '
                       f'{sensor.name!r} ({sensor.height} rings, columns a '
                       f'multiple of {sensor.width}, >=3 channels)')
    xyz = arr[:, ::w // sensor.width, :3].astype(np.float32)
    if not np.isfinite(xyz).all():
      raise ValueError(f'{path}: NaN or inf coordinates')
    depth = np.linalg.norm(xyz, axis=-1).astype(np.float32)
    return (depth, xyz, None) if return_xyz else (depth, None)
  raise ValueError(f'{path}: expected (N, >=4) points or an (H, W, >=3) grid, '
                   f'got shape {arr.shape}')
