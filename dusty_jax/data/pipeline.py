"""Training batches from prepared arrays, or from the simulated default."""

from __future__ import annotations

import hashlib
import json
import os

import numpy as np

from dusty_jax import codec, sensor as sensor_lib
from dusty_jax.data import arrays
from dusty_jax.sensor import SensorSpec


# CPU seconds per simulated 64x256 scan, all in (workers' start-up, writing):
# the default data (2,400 scans) took 24.1 s of CPU, parent and workers, and
# 12.4 s of wall time on a 2-core AMD EPYC VM at a load average of 1-3
# (benchmarks/synthesize.py --full, median of 3, results/synthesize.json,
# 2026-11-26).
SIMULATION_CPU_S = 0.010


def default_cache() -> str:
  return os.environ.get('DUSTY_JAX_CACHE',
                        os.path.join(os.path.expanduser('~'), '.cache', 'dusty_jax'))


def synthetic_dir(config, sensor: SensorSpec) -> str:
  cache = config.data.cache or default_cache()
  return os.path.join(cache, 'synthetic',
                      f'{sensor.name}_{sensor.height}x{sensor.width}{spec_key(sensor)}'
                      f'_n{config.data.num_synthetic}_s{config.data.seed}')


def spec_key(sensor: SensorSpec) -> str:
  """'' for a preset as it is (the cache names of earlier versions), else
  a hash of the spec: simulated scans are cached by the spec that rendered
  them, not by its name."""
  if sensor_lib.PRESETS.get(sensor.name) == sensor or sensor.name.startswith('tiny'):
    return ''
  digest = hashlib.sha1(json.dumps(sensor.to_dict(), sort_keys=True).encode())
  return '_' + digest.hexdigest()[:10]


def dataset_dir(config, sensor: SensorSpec, log=print) -> str:
  """The prepared dataset a config names; simulates the default once, cached.

  A config with no ``data.dir`` trains on simulated scans, generated on
  first use and cached under ``data.cache`` (default ~/.cache/dusty_jax).
  """
  if config.data.dir:
    directory = os.path.expanduser(config.data.dir)
    if not os.path.isfile(arrays.split_path(directory, 'train')):
      raise FileNotFoundError(
          f'{directory}: no prepared training split (train.npy). Prepare the '
          f'dataset first, e.g. `python -m dusty_jax.tools.prepare --dataset '
          f'{config.data.name or "kitti"} --root /path/to/raw --out {directory}`; '
          'or train on simulated scans with --config experiments/synthetic.py, '
          'which runs as is.')
    return directory
  directory = synthetic_dir(config, sensor)
  if not os.path.isfile(os.path.join(directory, arrays.META)):
    # Imported here: the simulator's import cost (about 1.5 s), paid only
    # when no cached dataset exists.
    from dusty_jax.data import synthetic
    n, workers = config.data.num_synthetic, max(os.cpu_count() or 1, 1)
    scans = n + 2 * max(n // 10, 1)  # train, val, test (write_dataset)
    log(f'simulating {n} training scans (+ val, test: {scans} in all) into '
        f'{directory}, once (cached): about {scans * SIMULATION_CPU_S / workers:.0f} s '
        f'with {workers} idle cores (the default 2,400 took 24 CPU-s on a 2-core '
        'AMD EPYC VM)')
    synthetic.write_dataset(directory, sensor, n, seed=config.data.seed,
                            workers=workers)
  return directory


class Batches:
  """Random batches of encoded scans, a pure function of (seed, step).

  Resuming at step k gives the batch an uninterrupted run saw at step k.
  Each process draws the whole global batch and keeps its own slice.
  """

  def __init__(self, depth: np.ndarray, sensor: SensorSpec, global_batch: int,
               seed: int, process_index: int = 0, process_count: int = 1):
    if global_batch % process_count:
      raise ValueError(f'batch_size={global_batch} does not split evenly over '
                       f'{process_count} processes')
    self.depth, self.sensor = depth, sensor
    self.global_batch, self.seed = global_batch, seed
    self.local = global_batch // process_count
    self.offset = process_index * self.local

  def __call__(self, step: int) -> np.ndarray:
    rng = np.random.default_rng((self.seed, step))
    # Sorted (contiguous reads from a memory-mapped file) before slicing, so
    # the process slices, in process order, are the single-process batch.
    idx = np.sort(rng.integers(0, len(self.depth), self.global_batch))
    idx = idx[self.offset:self.offset + self.local]
    return np.asarray(codec.encode(self.depth[idx], self.sensor))
