"""Turns a KITTI or MPO folder into prepared arrays (see data/arrays.py).

The command line is ``python -m dusty_jax.tools.prepare``.

One unreadable or malformed scan is reported and skipped, with a count at the
end; it never stops the conversion or drops silently. So is a scan with far
too few points to be a LiDAR scan (fewer than MIN_VALID_FRACTION of its
pixels valid, or returns on fewer than MIN_RING_FRACTION of its rings).
Arguments and inputs are checked before anything is created; a split that
now yields no scan has its old array removed (said so), and a run that finds
no scan at all fails. Each split is written scan by scan, so memory does not
grow with the number of scans (benchmarks/prepare_memory.py).
"""

from __future__ import annotations

import os
import sys
import warnings

import numpy as np
import tqdm

from dusty_jax import codec
from dusty_jax.data import arrays, kitti, mpo, unfolding
from dusty_jax.errors import DataError
from dusty_jax.sensor import SensorSpec, get_sensor

READERS = {'kitti': kitti, 'mpo': mpo}
SPLITS = ('train', 'val', 'test')
MIN_VALID_FRACTION = 0.05  # a real scan returns on most of its pixels
MIN_RING_FRACTION = 0.25


def junk_reason(depth, sensor: SensorSpec) -> str | None:
  """Why an unfolded scan is too sparse to train on, or None."""
  valid = np.asarray(codec.valid_depth(depth, sensor))
  frac = valid.mean()
  rings = int(valid.any(axis=1).sum())
  if frac < MIN_VALID_FRACTION:
    return (f'only {valid.sum()} valid pixels ({100 * frac:.2f}% < '
            f'{100 * MIN_VALID_FRACTION:.0f}%): not a full LiDAR scan')
  if rings < MIN_RING_FRACTION * sensor.height:
    return f'returns on only {rings} of {sensor.height} rings'
  return None


def convert_split(paths, load, sensor: SensorSpec, target: str, angle_acc=None,
                  desc='scans', log=print):
  """Converts files into the (N, H, W) depth array ``target``, scan by scan
  (memory does not grow with N); returns (N, skipped).

  ``skipped`` lists (path, reason) for every file that failed. With no scan,
  nothing is written (an old ``target`` is left for the caller to remove).
  """
  skipped = []
  writer = arrays.SplitWriter(target, len(paths), sensor.shape)
  try:
    for path in tqdm.tqdm(paths, desc=desc, unit='scan', file=sys.stderr,
                          disable=len(paths) < 2):
      try:
        with warnings.catch_warnings(record=True) as caught:
          warnings.simplefilter('always')
          depth, xyz, *_ = load(path, sensor, return_xyz=True)
        for w in caught:
          log(f'warning: {w.message}')
      except (ValueError, OSError) as e:
        skipped.append((path, str(e)))
        log(f'skipped: {e}')
        continue
      reason = junk_reason(depth, sensor)
      if reason:
        skipped.append((path, reason))
        log(f'skipped: {path}: {reason}')
        continue
      writer.append(depth)
      if angle_acc is not None:
        angle_acc.add(xyz)
  except BaseException:
    writer.abort()
    raise
  return writer.close(), skipped


def _kept_splits(out: str, splits, sensor: SensorSpec) -> dict:
  """{split: scans} of the arrays already in ``out`` that this run keeps (the
  splits it does not prepare); refuses ones of another sensor's shape, which
  meta.json could not describe beside the new ones."""
  kept = {}
  for split in SPLITS:
    path = arrays.split_path(out, split)
    if split in splits or not os.path.isfile(path):
      continue
    shape = np.load(path, mmap_mode='r').shape
    if tuple(shape[1:]) != tuple(sensor.shape):
      raise DataError(
          f'{out} already holds {split}.npy of shape {shape}, not of sensor '
          f'{sensor.name!r} {sensor.shape}; prepare every split '
          f'(--splits {",".join(SPLITS)}) or choose another --out')
    kept[split] = int(shape[0])
  return kept


def prepare(dataset: str, root: str, out: str, sensor: SensorSpec | None = None,
            splits=SPLITS, log=print) -> dict:
  """Prepares every split of ``dataset`` under ``root`` into ``out``.

  Every input is checked before anything is created. ``meta.json`` then
  describes every split array in ``out``: the ones written now, and those
  of an earlier run that this one leaves (``splits`` a subset).
  """
  if dataset not in READERS:
    raise ValueError(f'unknown dataset {dataset!r}; known: {sorted(READERS)}')
  unknown = [s for s in splits if s not in SPLITS]
  if unknown or not splits:
    raise ValueError(f'unknown splits {unknown}; known: {list(SPLITS)}')
  if not os.path.isdir(root):
    raise FileNotFoundError(f'{root}: no such directory')
  reader = READERS[dataset]
  sensor = sensor or get_sensor(dataset)
  listed = {split: reader.list_split(root, split) for split in splits}
  if not any(listed.values()):
    raise FileNotFoundError(f'{root}: no {dataset} scan files for splits '
                            f'{list(splits)} (is this the dataset root?)')
  kept = _kept_splits(out, splits, sensor)
  old = arrays.read_meta(out)
  os.makedirs(out, exist_ok=True)
  meta = {'dataset': dataset, 'sensor': sensor.name, 'shape': list(sensor.shape),
          'splits': dict(kept),
          'skipped': {s: old.get('skipped', {}).get(s, []) for s in kept}}
  acc = unfolding.AngleAccumulator(sensor)
  for split in splits:
    paths = listed[split]
    target = arrays.split_path(out, split)
    count, skipped = convert_split(
        paths, reader.load_scan, sensor, target,
        angle_acc=acc if split == 'train' else None, desc=split, log=log)
    if not count and os.path.isfile(target):
      os.remove(target)  # a stale array from an earlier run must not be used
      log(f'{split}: removed the old {target} (this run found no scan for it)')
    if not paths:
      log(f'{split}: no files found, split not written')
    meta['splits'][split] = int(count)
    meta['skipped'][split] = [{'path': p, 'reason': r} for p, r in skipped]
    log(f'{split}: {count} scans written, {len(skipped)} skipped')
  angles = os.path.join(out, arrays.ANGLES)
  if acc.count.sum():
    arrays.save_array(angles, acc.result())
  elif 'train' in splits and os.path.isfile(angles):
    os.remove(angles)
    log(f'removed the old {angles} (no training scan to estimate it from)')
  arrays.write_meta(out, meta)
  if not sum(meta['splits'][s] for s in splits):
    raise DataError(f'{root}: every scan file was skipped; nothing prepared '
                    '(see the reasons above)')
  return meta
