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

from dusty_jax.errors import DataError
from dusty_jax.sensor import SensorSpec, check_angles

ANGLES = 'angles.npy'
META = 'meta.json'


def split_path(directory: str, split: str, kind: str = '') -> str:
  return os.path.join(directory, f'{split}_{kind}.npy' if kind else f'{split}.npy')


def _check_shape(path, arr, sensor, lead):
  want = sensor.shape
  if arr.ndim != lead + 2 or tuple(arr.shape[-2:]) != want:
    raise DataError(f'{path}: array of shape {arr.shape} does not match sensor '
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
    raise DataError(f'{path}: the split holds no scans')
  return arr


def load_angles(directory: str, sensor: SensorSpec) -> np.ndarray:
  """(2, H, W) angle table of a prepared dataset (nominal if absent)."""
  path = os.path.join(directory, ANGLES)
  if not os.path.isfile(path):
    return sensor.nominal_angles()
  arr = np.load(path)
  try:
    check_angles(arr, sensor.shape, f'{path}: ', finite=True)
  except ValueError as e:
    raise DataError(str(e)) from None
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


def empty_array(path: str, shape) -> int:
  """Makes ``path`` a float32 .npy of ``shape`` (its data not yet written)
  and returns the offset of its data in the file."""
  np.lib.format.open_memmap(path, mode='w+', dtype=np.float32, shape=tuple(shape)).flush()
  with open(path, 'rb') as f:
    np.lib.format.read_magic(f)
    np.lib.format.read_array_header_1_0(f)
    return f.tell()


class SplitWriter:
  """Writes an (N, H, W) float32 split scan by scan, so memory does not grow
  with N: at most ``capacity`` scans, into a temporary .npy (header from
  ``np.lib.format.open_memmap``, rows appended with plain writes, which keep
  nothing resident), then :meth:`close` sets the header to the scans
  written, cuts the file there and moves it into place atomically.
  """

  def __init__(self, path: str, capacity: int, shape):
    self.path, self.tmp = path, path + '.tmp.npy'
    self.shape, self.count = tuple(shape), 0
    self.capacity = capacity
    self.offset = empty_array(self.tmp, (capacity,) + self.shape)
    self.file = open(self.tmp, 'r+b')
    self.file.seek(self.offset)

  def append(self, scan: np.ndarray):
    if self.count == self.capacity:
      raise ValueError(f'{self.path}: more than the {self.capacity} scans announced')
    scan = np.ascontiguousarray(scan, np.float32)
    if scan.shape != self.shape:
      raise ValueError(f'scan of shape {scan.shape}, expected {self.shape}')
    self.file.write(scan.tobytes())
    self.count += 1

  def close(self) -> int:
    """Finishes the file (when any scan was written; else removes it) and
    returns the number of scans."""
    header = _npy_header((self.count,) + self.shape, self.offset)
    self.file.seek(0)
    self.file.write(header)
    self.file.truncate(self.offset + self.count * int(np.prod(self.shape)) * 4)
    self.file.close()
    if self.count:
      os.replace(self.tmp, self.path)
    else:
      os.remove(self.tmp)
    return self.count

  def abort(self):
    self.file.close()
    if os.path.exists(self.tmp):
      os.remove(self.tmp)


def _npy_header(shape, length: int) -> bytes:
  """A version 1.0 .npy header of float32 ``shape``, padded with spaces to
  ``length`` bytes (the data after it stays where it is)."""
  d = repr({'descr': '<f4', 'fortran_order': False, 'shape': tuple(shape)})
  body_len = length - 10  # magic (6), version (2), header length (2)
  if len(d) + 1 > body_len:
    raise ValueError(f'a header for shape {shape} does not fit in {length} bytes')
  body = (d + ' ' * (body_len - len(d) - 1) + '\n').encode('latin1')
  return b'\x93NUMPY\x01\x00' + body_len.to_bytes(2, 'little') + body
