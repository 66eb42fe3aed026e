"""Prepared arrays: the on-disk format that training and evaluation read.

A prepared dataset is a directory holding, per split, ``{split}.npy``: metric
depth shaped (N, H, W), float32, 0 where there was no return (memory-mapped
when read), plus ``angles.npy`` (2, H, W): the per-pixel elevation and azimuth
estimated from the training split, and ``meta.json``. Simulated datasets add
the ground truth beside each split: ``{split}_complete.npy`` (the depth a
perfect sensor sees) and ``{split}_drop_prob.npy`` (the true probability of
each point-drop).
"""

from __future__ import annotations

import json
import os

import numpy as np

from dusty_jax.sensor import SensorSpec

ANGLES = 'angles.npy'
META = 'meta.json'


def split_path(directory: str, split: str, kind: str = '') -> str:
  return os.path.join(directory, f'{split}_{kind}.npy' if kind else f'{split}.npy')


def _check_shape(path, arr, sensor, lead):
  want = sensor.shape
  if arr.ndim != lead + 2 or tuple(arr.shape[-2:]) != want:
    raise ValueError(f'{path}: array of shape {arr.shape} does not match sensor '
                     f'{sensor.name!r} (expected (..., {want[0]}, {want[1]}))')


def load_split(directory: str, split: str, sensor: SensorSpec,
               kind: str = '') -> np.ndarray:
  """Memory-mapped (N, H, W) array of a split, checked against the sensor."""
  path = split_path(directory, split, kind)
  if not os.path.isfile(path):
    raise FileNotFoundError(
        f'{path}: no prepared {split!r} split here. Prepare real data with '
        '`python -m dusty_jax.tools.prepare --dataset kitti --root DIR --out DIR`, '
        'or simulate some with `python -m dusty_jax.tools.synthesize`.')
  arr = np.load(path, mmap_mode='r')
  _check_shape(path, arr, sensor, lead=1)
  if arr.shape[0] == 0:
    raise ValueError(f'{path}: the split holds no scans')
  return arr


def load_angles(directory: str, sensor: SensorSpec) -> np.ndarray:
  """(2, H, W) angle table of a prepared dataset (nominal if absent)."""
  path = os.path.join(directory, ANGLES)
  if not os.path.isfile(path):
    return sensor.nominal_angles()
  arr = np.load(path)
  _check_shape(path, arr, sensor, lead=1)
  if arr.shape[0] != 2 or not np.isfinite(arr).all():
    raise ValueError(f'{path}: expected finite (2, H, W) elevation/azimuth')
  return arr.astype(np.float32)


def load_ground_truth(directory: str, split: str, sensor: SensorSpec, num: int):
  """(complete depth, drop probability) of a simulated split's first ``num``
  scans, or None where the split has no ground truth (real data)."""
  try:
    return (np.asarray(load_split(directory, split, sensor, 'complete')[:num]),
            np.asarray(load_split(directory, split, sensor, 'drop_prob')[:num]))
  except FileNotFoundError:
    return None


def read_meta(directory: str) -> dict:
  path = os.path.join(directory, META)
  if not os.path.isfile(path):
    return {}
  with open(path) as f:
    return json.load(f)


def write_meta(directory: str, meta: dict):
  os.makedirs(directory, exist_ok=True)
  tmp = os.path.join(directory, META + '.tmp')
  with open(tmp, 'w') as f:
    json.dump(meta, f, indent=2, sort_keys=True)
  os.replace(tmp, os.path.join(directory, META))


def save_array(path: str, arr: np.ndarray):
  """Writes atomically: a half-written file never replaces a good one."""
  tmp = path + '.tmp.npy'
  np.save(tmp, np.ascontiguousarray(arr))
  os.replace(tmp, path)
