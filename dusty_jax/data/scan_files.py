"""Scans given as files by a user: KITTI ``.bin`` or ``.npy`` metric depth."""

from __future__ import annotations

import os

import numpy as np

from dusty_jax.data import kitti
from dusty_jax.errors import DataError
from dusty_jax.sensor import SensorSpec

# What tools/invert.py writes per scan beside the re-rendered metric depth
# (NAME_depth.npy, a scan like any other): not metric depth, so not inputs.
INVERT_OUTPUTS = {'_inv_depth.npy': 'normalised inverse depth (x_tilde)',
                  '_measurability.npy': 'measurability'}


def unusable_reason(depth: np.ndarray, sensor: SensorSpec) -> str | None:
  """Why a metric depth scan cannot be fitted, or None: no pixel inside the
  sensor's range, or fewer than half of its returns (nonzero finite
  depths), as normalised or encoded values given as metres have."""
  finite = depth[np.isfinite(depth)]
  returns = finite[finite != 0]
  if not returns.size:
    return 'no return: every depth is 0 or not finite'
  share = np.mean((returns > sensor.min_depth) & (returns < sensor.max_depth))
  if share >= 0.5:
    return None
  lo, hi = float(returns.min()), float(returns.max())
  where = (f'every depth is below the sensor\'s minimum range of {sensor.min_depth} m'
           if hi <= sensor.min_depth else
           f'{share:.0%} of the returns lie inside the sensor\'s range '
           f'({sensor.min_depth}, {sensor.max_depth}) m')
  return (f'{where} (values in [{lo:.3g}, {hi:.3g}]): normalised or already encoded '
          'scans given as metres? The input takes metric depth')


def _load_npy(path: str) -> np.ndarray:
  """The array of a .npy file; ValueError naming the file for anything else."""
  if not path.endswith('.npy'):
    raise ValueError(f'{path}: not a scan file; give KITTI .bin files or .npy '
                     'files of metric depth')
  for suffix, what in INVERT_OUTPUTS.items():
    if path.endswith(suffix):
      stem = os.path.basename(path[:-len(suffix)])
      raise ValueError(f"{path}: invert's {what}, not metric depth ({stem}_depth.npy "
                       'is its scan in metres)')
  try:
    arr = np.load(path, allow_pickle=False)
  except ValueError:  # pickled objects, or not an array file at all
    raise ValueError(f'{path}: not a .npy array of numbers (metric depth)') from None
  if not isinstance(arr, np.ndarray):
    arr.close()
    raise ValueError(f'{path}: a .npz archive, not a .npy array of metric depth')
  return arr


def read_scans(path: str, sensor: SensorSpec, log=print):
  """[(name, metric depth (H, W))] from a file or a directory of files.

  ``.bin`` files are unfolded with the sensor; ``.npy`` files hold metric
  depth (H, W) or (N, H, W); of those, invert's outputs that are not depth
  (INVERT_OUTPUTS) are skipped. A file that cannot be read, or a scan with
  fewer than half of its returns inside the sensor's range
  (:func:`unusable_reason`: e.g. encoded scans given as metres), is reported with its file and skipped (and counted), as
  prepare does; only no usable scan at all fails.
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
  out, skipped, bad_files = [], [], 0
  for f in files:
    stem = os.path.splitext(os.path.basename(f))[0]
    try:
      if f.endswith('.bin'):
        depth, _ = kitti.load_scan(f, sensor)
        scans = [(stem, f, depth)]
      else:
        arr = _load_npy(f)
        if arr.shape[-2:] != sensor.shape or arr.ndim not in (2, 3):
          raise ValueError(f'{f}: expected metric depth of shape (H, W) or '
                           f'(N, H, W) with H, W = {sensor.shape}, got {arr.shape}')
        scans = ([(stem, f, arr)] if arr.ndim == 2 else
                 [(f'{stem}_{i:05d}', f'{f}[{i}]', a) for i, a in enumerate(arr)])
    except (ValueError, OSError) as e:
      skipped.append((f, str(e)))
      bad_files += 1
      log(f'skipped: {e}')
      continue
    for name, where, depth in scans:
      reason = unusable_reason(np.asarray(depth), sensor)
      if reason:
        skipped.append((where, reason))
        log(f'skipped: {where}: {reason}')
      else:
        out.append((name, depth))
  if not out:
    raise DataError(f'{path}: none of {len(files)} input files could be read or '
                    'holds a scan to fit (see the reasons above)')
  if bad_files:
    log(f'{bad_files} of {len(files)} input files skipped')
  if len(skipped) > bad_files:
    log(f'{len(skipped) - bad_files} scans with too few returns in range skipped')
  return out
