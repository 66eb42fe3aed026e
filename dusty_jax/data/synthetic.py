"""The embedded default data: a dataset of simulated LiDAR scans.

Each scan is simulated_lidar.render_scan of a procedural scene (scene.py);
:func:`write_dataset` writes them in the prepared-array format
(data/arrays.py) with their ground truth (complete depth, drop probability),
in parallel processes, plus a preview picture.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import tqdm

from dusty_jax import codec
from dusty_jax.data import arrays, kitti, simulated_lidar
from dusty_jax.sensor import SensorSpec


def _render_arrays(args):
  seed, sensor = args
  s = simulated_lidar.render_scan(seed, sensor)
  return s.depth, s.complete, s.drop_prob


def simulate(num: int, sensor: SensorSpec, seed: int = 0, progress: bool = True,
             desc: str = 'simulating', workers: int = 1):
  """(observed, complete, drop_prob) arrays of ``num`` scans, (N, H, W) each.

  Scan i uses scene seed ``seed * 1_000_003 + i``: the result does not depend
  on ``workers``.
  """
  shape = (num,) + sensor.shape
  out = [np.zeros(shape, np.float32) for _ in range(3)]
  jobs = [(seed * 1_000_003 + i, sensor) for i in range(num)]
  bar = tqdm.tqdm(total=num, desc=desc, unit='scan', file=sys.stderr,
                  disable=not progress)
  if workers > 1 and num > 1:
    import multiprocessing
    # Forking a process that runs JAX's threads can deadlock: spawn then.
    method = 'spawn' if 'jax' in sys.modules else 'fork'
    with multiprocessing.get_context(method).Pool(workers) as pool:
      results = pool.imap(_render_arrays, jobs, chunksize=16)
      for i, r in enumerate(results):
        out[0][i], out[1][i], out[2][i] = r
        bar.update()
  else:
    for i, job in enumerate(jobs):
      out[0][i], out[1][i], out[2][i] = _render_arrays(job)
      bar.update()
  bar.close()
  return tuple(out)


SPLIT_SEED_OFFSET = {'train': 0, 'val': 1, 'test': 2}


def write_dataset(out: str, sensor: SensorSpec, num: int, seed: int = 0,
                  splits: dict | None = None, bins: bool = False,
                  progress: bool = True, workers: int = 1) -> dict:
  """Simulates a prepared dataset (see data/arrays.py) with ground truth.

  ``splits`` maps split name to size (default: ``num`` train, num // 10 val
  and test). With ``bins``, every scan is also written as a KITTI ``.bin``
  in sensor order under ``out/kitti/sequences/NN/velodyne`` (train 00, val
  08, test 11) so the real-data path can be exercised on it.
  """
  splits = splits or {'train': num, 'val': max(num // 10, 1),
                      'test': max(num // 10, 1)}
  os.makedirs(out, exist_ok=True)
  seq = {'train': 0, 'val': 8, 'test': 11}
  for split, n in splits.items():
    obs, complete, prob = simulate(
        n, sensor, seed=seed * 10 + SPLIT_SEED_OFFSET[split], progress=progress,
        desc=split, workers=workers)
    arrays.save_array(arrays.split_path(out, split), obs)
    arrays.save_array(arrays.split_path(out, split, 'complete'), complete)
    arrays.save_array(arrays.split_path(out, split, 'drop_prob'), prob)
    if bins:
      for i, d in enumerate(obs):
        kitti.write_bin(os.path.join(out, 'kitti', 'sequences',
                                     f'{seq[split]:02d}', 'velodyne',
                                     f'{i:06d}.bin'), simulated_lidar.to_sensor_order(d, sensor))
  arrays.save_array(os.path.join(out, arrays.ANGLES), sensor.nominal_angles())
  save_preview(os.path.join(out, 'preview.png'), out, sensor)
  meta = {'dataset': 'synthetic', 'sensor': sensor.name,
          'shape': list(sensor.shape), 'seed': seed,
          'splits': {k: int(v) for k, v in splits.items()}}
  arrays.write_meta(out, meta)
  return meta


def save_preview(path: str, directory: str, sensor: SensorSpec, num: int = 4):
  """PNG of observed depth, complete depth and drop probability, per scan."""
  from dusty_jax import writers  # here: matplotlib's import cost, for a preview only
  obs = arrays.load_split(directory, 'train', sensor)[:num]
  comp = arrays.load_split(directory, 'train', sensor, 'complete')[:num]
  prob = arrays.load_split(directory, 'train', sensor, 'drop_prob')[:num]
  rows = []
  for o, c, p in zip(obs, comp, prob):
    rows.append([writers.inv_depth_tile(np.asarray(codec.encode(o, sensor)))])
    rows.append([writers.inv_depth_tile(np.asarray(codec.encode(c, sensor)))])
    rows.append([writers.prob_tile(p)])
  writers.save_grid(path, rows, scale=2)
