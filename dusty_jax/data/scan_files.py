"""Scans given as files by a user: KITTI ``.bin`` or ``.npy`` metric depth."""

from __future__ import annotations

import os

import numpy as np

from dusty_jax.data import kitti
from dusty_jax.sensor import SensorSpec


def read_scans(path: str, sensor: SensorSpec, log=print):
  """[(name, metric depth (H, W))] from a file or a directory of files.

  ``.bin`` files are unfolded with the sensor; ``.npy`` files hold metric
  depth (H, W) or (N, H, W). A file that cannot be read is reported and
  skipped (and counted), as prepare does; only no readable file fails.
  """
  if os.path.isdir(path):
    files = sorted(os.path.join(path, f) for f in os.listdir(path)
                   if f.endswith(('.bin', '.npy')))
    if not files:
      raise FileNotFoundError(f'{path}: no .bin or .npy files')
  elif os.path.isfile(path):
    files = [path]
  else:
    raise FileNotFoundError(f'{path}: no such file or directory')
  out, skipped = [], []
  for f in files:
    stem = os.path.splitext(os.path.basename(f))[0]
    try:
      if f.endswith('.bin'):
        depth, _ = kitti.load_scan(f, sensor)
        out.append((stem, depth))
        continue
      arr = np.load(f, allow_pickle=False)
      if arr.shape[-2:] != sensor.shape or arr.ndim not in (2, 3):
        raise ValueError(f'{f}: expected metric depth of shape (H, W) or '
                         f'(N, H, W) with H, W = {sensor.shape}, got {arr.shape}')
    except (ValueError, OSError) as e:
      skipped.append((f, str(e)))
      log(f'skipped: {e}')
      continue
    if arr.ndim == 2:
      out.append((stem, arr))
    else:
      out += [(f'{stem}_{i:05d}', a) for i, a in enumerate(arr)]
  if not out:
    raise ValueError(f'{path}: none of {len(files)} input files could be read')
  if skipped:
    log(f'{len(skipped)} of {len(files)} input files skipped')
  return out
