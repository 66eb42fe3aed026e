"""The embedded default data: a dataset of simulated LiDAR scans.

Each scan is simulated_lidar.render_scan of a procedural scene (scene.py);
:func:`write_dataset` writes them in the prepared-array format
(data/arrays.py) with their ground truth (complete depth, drop probability),
in parallel processes, plus a preview picture.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import sys
import types

import numpy as np
import tqdm

from dusty_jax import files
from dusty_jax.data import arrays, identity, scene, simulated_lidar
from dusty_jax.sensor import SensorSpec

# Scans a worker renders per task: few enough to keep both of two workers busy
# to the end of a 200-scan split, many enough to send few tasks.
_CHUNK = 8


@contextlib.contextmanager
def _rendered(jobs: list, workers: int, task=simulated_lidar.render_arrays):
  """Yields ``task(job)`` of each job, in order (by default the (observed,
  complete, drop_prob) of each (seed, sensor)), run by ``workers`` processes.

  They are forked where JAX is not loaded and spawned where it is (forking a
  process that runs JAX's threads can deadlock). A spawned worker imports
  simulated_lidar (trimesh, not JAX) and nothing else: not the parent's main
  module, which under ``python -m dusty_jax.train`` would load the trainer
  and JAX into every worker (1.5 s more to start two), and which a main read
  from stdin could not give it at all.
  """
  if workers <= 1 or len(jobs) <= 1:
    yield map(task, jobs)
    return
  if 'jax' in sys.modules:
    with _without_main():  # the workers start here, in Pool()
      pool = multiprocessing.get_context('spawn').Pool(workers)
  else:
    pool = multiprocessing.get_context('fork').Pool(workers)
  with pool:
    yield pool.imap(task, jobs, chunksize=_CHUNK)


@contextlib.contextmanager
def _without_main():
  """While it lasts, ``__main__`` is an empty module: what a process spawned
  then is told to import as its main (multiprocessing.spawn). The workers'
  tasks and results name nothing in ``__main__``. A worker that the pool
  starts later, in place of one that crashed, imports the real main; the
  crashed worker's task is lost then anyway (Pool.imap waits for it)."""
  main = sys.modules['__main__']
  sys.modules['__main__'] = types.ModuleType('__main__')
  try:
    yield
  finally:
    sys.modules['__main__'] = main


def scene_seeds(num: int, seed: int) -> list[int]:
  """The scene seeds of ``num`` scans of dataset seed ``seed``: scan i is
  scene ``seed * 1_000_003 + i``."""
  return [seed * 1_000_003 + i for i in range(num)]


def _jobs(num: int, sensor: SensorSpec, seed: int) -> list:
  return [(s, sensor) for s in scene_seeds(num, seed)]


def _collect(results, num: int, sensor: SensorSpec, progress: bool, desc: str):
  """The next ``num`` of ``results`` as three (num, H, W) float32 arrays."""
  out = [np.zeros((num,) + sensor.shape, np.float32) for _ in range(3)]
  bar = tqdm.tqdm(total=num, desc=desc, unit='scan', file=sys.stderr,
                  disable=not progress)
  for i in range(num):
    out[0][i], out[1][i], out[2][i] = next(results)
    bar.update()
  bar.close()
  return tuple(out)


def simulate(num: int, sensor: SensorSpec, seed: int = 0, progress: bool = True,
             desc: str = 'simulating', workers: int = 1):
  """(observed, complete, drop_prob) arrays of ``num`` scans, (N, H, W) each.

  Scan i uses scene seed ``seed * 1_000_003 + i``: the result does not depend
  on ``workers``.
  """
  with _rendered(_jobs(num, sensor, seed), workers) as results:
    return _collect(results, num, sensor, progress, desc)


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
  if os.path.exists(out) and not os.path.isdir(out):
    raise NotADirectoryError(f'{out}: a file, not a folder; give a folder for the dataset')
  os.makedirs(out, exist_ok=True)
  seq = {'train': 0, 'val': 8, 'test': 11}
  # Each split's three arrays are made here as temporary .npy files, and the
  # workers write each scan into them; one pool for all splits. The files
  # are this call's own (files.atomic_path): the processes of a multi-process
  # training simulate the same data into the same folder at once, each
  # moving its files into place whole, once every scan is written.
  paths = {split: tuple(arrays.split_path(out, split, kind) for kind in ('', 'complete',
                                                                         'drop_prob'))
           for split in splits}
  with contextlib.ExitStack() as written:
    jobs = []
    for split, n in splits.items():
      tmps = tuple(written.enter_context(files.atomic_path(p, '.npy')) for p in paths[split])
      for tmp in tmps:  # (one shape: one data offset for the three)
        offset = arrays.empty_array(tmp, (n,) + sensor.shape)
      jobs += [(s, sensor_, tmps, offset, i)
               for i, (s, sensor_) in enumerate(_jobs(n, sensor, seed * 10 +
                                                      SPLIT_SEED_OFFSET[split]))]
    with _rendered(jobs, workers, simulated_lidar.render_into) as done:
      for split, n in splits.items():
        for _ in tqdm.trange(n, desc=split, unit='scan', file=sys.stderr,
                             disable=not progress):
          next(done)
  if bins:
    # Here: kitti imports JAX (through unfolding and codec); at the top, it
    # would make every pool of _rendered spawn rather than fork.
    from dusty_jax.data import kitti
    for split in splits:
      for i, d in enumerate(np.load(paths[split][0], mmap_mode='r')):
        kitti.write_bin(os.path.join(out, 'kitti', 'sequences', f'{seq[split]:02d}',
                                     'velodyne', f'{i:06d}.bin'),
                        simulated_lidar.to_sensor_order(np.asarray(d), sensor))
  arrays.save_array(os.path.join(out, arrays.ANGLES), sensor.nominal_angles())
  save_preview(os.path.join(out, 'preview.png'), out, sensor)
  meta = {'dataset': 'synthetic', 'sensor': sensor.name,
          'shape': list(sensor.shape), 'seed': seed,
          'splits': {k: int(v) for k, v in splits.items()},
          # what each observed split is, for training to check (identity.py)
          'identity': {k: identity.of_file(paths[k][0], whole=True) for k in splits}}
  arrays.write_meta(out, meta)
  return meta


def scene_kinds(directory: str, split: str) -> np.ndarray:
  """(N,) the scene kind (scene.SCENE_KINDS) of each scan of a split that
  :func:`write_dataset` simulated into ``directory``, recovered from the
  seeds its meta.json records (scene.kind_of). Refuses other datasets."""
  meta = arrays.read_meta(directory)
  if meta.get('dataset') != 'synthetic' or split not in meta.get('splits', {}):
    raise ValueError(f'{directory}: no simulated {split!r} split recorded in its '
                     f'{arrays.META} (scene kinds are known for simulated data only)')
  seeds = scene_seeds(meta['splits'][split], meta['seed'] * 10 + SPLIT_SEED_OFFSET[split])
  return np.array([scene.kind_of(s) for s in seeds])


def save_preview(path: str, directory: str, sensor: SensorSpec, num: int = 4):
  """PNG of observed depth, complete depth and drop probability, per scan."""
  # Here: the import cost of matplotlib and of JAX (codec), for a preview only.
  from dusty_jax import codec, writers
  obs = arrays.load_split(directory, 'train', sensor)[:num]
  comp = arrays.load_split(directory, 'train', sensor, 'complete')[:num]
  prob = arrays.load_split(directory, 'train', sensor, 'drop_prob')[:num]
  fig = writers.scan_figure(
      [writers.Column('observed scan', writers.DEPTH, np.asarray(codec.encode(obs, sensor))),
       writers.Column('complete depth', writers.DEPTH, np.asarray(codec.encode(comp, sensor))),
       writers.Column('drop probability', writers.PROBABILITY, prob,
                      'probability of a drop')],
      sensor, row_label='training scan')
  writers.save_figure(fig, path)
