"""Turns a KITTI or MPO folder into prepared arrays (see data/arrays.py).

    python -m dusty_jax.prepare --dataset kitti --root /data/kitti --out data/kitti

One unreadable or malformed scan is reported and skipped, with a count at the
end; it never stops the conversion or drops silently.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

import numpy as np
import tqdm

from dusty_jax import projection
from dusty_jax.data import arrays, kitti, mpo
from dusty_jax.sensor import SensorSpec, get_sensor

READERS = {'kitti': kitti, 'mpo': mpo}
SPLITS = ('train', 'val', 'test')


def convert_split(paths, load, sensor: SensorSpec, angle_acc=None,
                  desc='scans', log=print):
  """Converts files to an (N, H, W) depth array; returns (array, skipped).

  ``skipped`` lists (path, reason) for every file that failed.
  """
  depths, skipped = [], []
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
    depths.append(depth)
    if angle_acc is not None:
      angle_acc.add(xyz)
  out = (np.stack(depths).astype(np.float32) if depths
         else np.zeros((0,) + sensor.shape, np.float32))
  return out, skipped


def prepare(dataset: str, root: str, out: str, sensor: SensorSpec | None = None,
            splits=SPLITS, log=print) -> dict:
  """Prepares every split of ``dataset`` under ``root`` into ``out``."""
  if dataset not in READERS:
    raise ValueError(f'unknown dataset {dataset!r}; known: {sorted(READERS)}')
  if not os.path.isdir(root):
    raise FileNotFoundError(f'{root}: no such directory')
  reader = READERS[dataset]
  sensor = sensor or get_sensor(dataset)
  os.makedirs(out, exist_ok=True)
  meta = {'dataset': dataset, 'sensor': sensor.name, 'shape': list(sensor.shape),
          'splits': {}, 'skipped': {}}
  acc = projection.AngleAccumulator(sensor)
  for split in splits:
    paths = reader.list_split(root, split)
    if not paths:
      log(f'{split}: no files found, split not written')
      continue
    depth, skipped = convert_split(
        paths, reader.load_scan, sensor,
        angle_acc=acc if split == 'train' else None, desc=split, log=log)
    if len(depth):
      arrays.save_array(arrays.split_path(out, split), depth)
    meta['splits'][split] = int(len(depth))
    meta['skipped'][split] = [{'path': p, 'reason': r} for p, r in skipped]
    log(f'{split}: {len(depth)} scans written, {len(skipped)} skipped')
  if acc.count.sum():
    arrays.save_array(os.path.join(out, arrays.ANGLES), acc.result())
  arrays.write_meta(out, meta)
  return meta


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--dataset', required=True, help='kitti or mpo')
  parser.add_argument('--root', required=True, help='dataset root folder')
  parser.add_argument('--out', required=True, help='output folder')
  parser.add_argument('--splits', default=','.join(SPLITS))
  args = parser.parse_args(argv)
  try:
    meta = prepare(args.dataset, args.root, args.out,
                   splits=tuple(args.splits.split(',')))
  except (ValueError, FileNotFoundError) as e:
    sys.exit(f'error: {e}')
  total_skipped = sum(len(v) for v in meta['skipped'].values())
  print(f'done: {meta["splits"]} -> {args.out}; {total_skipped} files skipped')


if __name__ == '__main__':
  main()
