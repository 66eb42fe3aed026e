"""Training batches from prepared arrays, or from the simulated default."""

from __future__ import annotations

import hashlib
import json
import os
import time

import numpy as np

from dusty_jax import codec, files, sensor as sensor_lib
from dusty_jax.data import arrays, identity
from dusty_jax.errors import DataError
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
  if sensor_lib.PRESETS.get(sensor.name) == sensor:
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
  damage = _cache_damage(directory)
  if damage:
    log(f'the cached simulated data in {directory} is not what was simulated '
        f'({damage}); simulating it again')
  if damage or not os.path.isfile(os.path.join(directory, arrays.META)):
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


def _cache_damage(directory: str) -> str | None:
  """What is wrong with a cached simulated dataset whose meta.json records
  its files (identity.py), or None: it is ours to simulate again."""
  recorded = arrays.read_meta(directory).get('identity', {})
  for split, ident in recorded.items():
    path = arrays.split_path(directory, split)
    try:
      changes = identity.differences(ident, identity.of_file(path))
    except (OSError, DataError) as e:
      return f'{os.path.basename(path)}: {e}'
    if changes:
      return f"{os.path.basename(path)}: {', '.join(changes)}"
  return None


class TrainingData:
  """The training split as a run reads it, and what the run knows of it.

  ``depth`` (N, H, W): in memory where the file is at most ``memory_mb``
  (the log says which), else read from the file batch by batch
  (arrays.FileRows); checked for bad values (arrays.check_values) before
  training. Its identity (identity.py) is compared with meta.json's record,
  kept in the run directory (RUN_FILE) by :meth:`start_run`, which refuses a
  resume onto other data unless allowed, and compared again by
  :meth:`check` at each log step.
  """

  RUN_FILE = 'data.json'

  def __init__(self, directory: str, sensor: SensorSpec, memory_mb: int, log=print):
    self.path = os.path.abspath(arrays.split_path(directory, 'train'))
    self.depth = arrays.read_split(directory, 'train', sensor, memory_mb << 20)
    self.in_memory = isinstance(self.depth, np.ndarray)
    size = os.path.getsize(self.path)
    log(f'{self.path}: {len(self.depth):,} training scans, {size / 2**20:,.1f} MiB, ' +
        ('read into memory' if self.in_memory else
         f'read from the file batch by batch (above data.memory_mb={memory_mb})'))
    arrays.check_values(self.depth, sensor, self.path, log)
    self.identity = identity.of_file(self.path, whole=self.in_memory,
                                     data=self.depth if self.in_memory else None)
    self._seen = identity.stat_key(self.path)
    self.switched = None  # what changed since the run's last start, if allowed
    recorded = arrays.read_meta(directory).get('identity', {}).get('train')
    changes = recorded and identity.differences(recorded, self.identity)
    if changes:
      log(f'warning: {self.path} is not the file meta.json records ({", ".join(changes)}); '
          'training on it as it is')

  def start_run(self, workdir: str, resuming: bool, allow_changed: bool, write: bool):
    """Compares the data with what the run in ``workdir`` trained on (when it
    ``resuming``) and refuses other data unless ``allow_changed``; then
    records it there (``write``: the process that writes the run's files).
    ``self.switched`` says what changed when other data was allowed."""
    path = os.path.join(workdir, self.RUN_FILE)
    record = {}
    if resuming and os.path.isfile(path):
      with open(path) as f:
        try:
          record = json.load(f)
        except json.JSONDecodeError:
          record = {}  # cut short by a kill: the run's data is retaken below
    before = record.get('identity')
    if resuming and before:
      changes = identity.differences(before, self.identity)
      if changes and record.get('file') != self.path:  # (the same bytes moved: the same data)
        changes.insert(0, f"file {record.get('file')} -> {self.path}")
      if changes and not allow_changed:
        raise DataError(
            f'{workdir} was trained on other data than {self.path} holds now '
            f'({", ".join(changes)}); restore that data to resume, or rerun with '
            '--config.data.allow_changed=true to go on training on this data '
            '(the metrics record the switch)')
      if changes:
        self.switched = ', '.join(changes)
        record.setdefault('switches', []).append(
            {'time': identity.when(time.time_ns()), 'from': before, 'to': self.identity,
             'changes': self.switched})
    if write:
      record.update(file=self.path, identity=self.identity)
      with files.atomic_write(path) as f:
        json.dump(record, f, indent=2)

  def changed(self) -> str | None:
    """What changed in the split's file since the start, or None. One stat
    when nothing did; the file is read (a sample, or all of it when the run
    holds it in memory) only when the stat differs."""
    try:
      key = identity.stat_key(self.path)
    except FileNotFoundError:
      return 'removed'
    if key == self._seen:
      return None
    try:
      now = identity.of_file(self.path, whole='sha256' in self.identity)
    except DataError:
      return f'{key[0]:,} bytes, no longer a .npy array'
    except OSError as e:
      return f'no longer readable ({e.strerror or e})'
    changes = identity.differences(self.identity, now)
    if not changes:
      self._seen = key  # touched, or replaced by the same bytes
      return None
    return ', '.join(changes)

  def check(self, step: int, last_checkpoint: int | None, agree=lambda text: [text]):
    """Stops training (a DataError) when the split's file changed; called
    at each log step and before each checkpoint, so no checkpoint is saved
    after it. ``agree``: every process's text of one (parallel.all_texts in
    a run of several), so that all stop together."""
    texts = agree(self.changed() or '')
    if not any(texts):
      return
    kept = ('no checkpoint was saved yet' if last_checkpoint is None else
            f'the last checkpoint, step {last_checkpoint}, was trained on the old data')
    raise DataError(
        f'{self.path} changed during training ({next(t for t in texts if t)}); stopped '
        f'at step {step}, before saving; {kept}. Restore the data and rerun to resume, '
        'or rerun with --config.data.allow_changed=true to go on training on the new data')


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
    # Sorted (contiguous reads from a file: arrays.FileRows) before slicing, so
    # the process slices, in process order, are the single-process batch.
    idx = np.sort(rng.integers(0, len(self.depth), self.global_batch))
    idx = idx[self.offset:self.offset + self.local]
    return np.asarray(codec.encode(self.depth[idx], self.sensor))
