"""Turns a dataset folder (KITTI, MPO, KITTI-360, nuScenes: kitti.py,
mpo.py, kitti360.py, nuscenes.py), or a folder of point files and
recordings of any spinning LiDAR (``files``: every format data/points.py
reads, and ROS bags and Velodyne captures, data/recordings.py: each sweep a
scan), into prepared arrays (see data/arrays.py), with the sensor spec they
were unfolded with beside them (``sensor.json``; estimated from the sweeps
with ``auto_sensor=True``, ``--sensor auto``).

The command line is ``python -m dusty_jax.tools.prepare``.

One unreadable or malformed scan is reported and skipped, with a count at the
end; it never stops the conversion or drops silently. So is a scan with far
too few points to be a LiDAR scan (fewer than MIN_VALID_FRACTION of its
pixels valid, or returns on fewer than MIN_RING_FRACTION of its rings), and
a sweep of another sensor (unfolding.NotThisSensor: its returns fill far
fewer pixels than the spec's sensor would; counted apart).
Arguments and inputs are checked before anything is created; a split that
now yields no scan has its old array removed (said so), and a run that finds
no scan at all fails, naming the first file's reason, and changes nothing
(an ``out`` it made is removed again). Each split is written scan by scan, so memory does not grow
with the number of scans (benchmarks/prepare_memory.py).
"""

from __future__ import annotations

import collections
import fnmatch
import itertools
import os
import shutil
import sys
import warnings

import numpy as np
import tqdm

from dusty_jax import codec, sensor as sensor_lib
from dusty_jax.data import (arrays, estimate, identity, kitti, kitti360, mpo, nuscenes, points,
                            recordings, unfolding)
from dusty_jax.errors import DataError
from dusty_jax.sensor import SensorSpec

SPLITS = ('train', 'val', 'test')
SENSOR_FILE = arrays.SENSOR  # the spec a prepared folder was unfolded with
# A seeded split of a folder of files: the share of each split.
FILE_SPLIT = {'train': 0.8, 'val': 0.1, 'test': 0.1}
ESTIMATE_SWEEPS = 8  # training sweeps that --sensor auto estimates from
# A sweep that loses more than this share of its points off the spec's beams
# or range is reported (its counts logged).
REPORT_DROPPED = 0.1


class Files:
  """A folder of point files (one sweep each, any format points.read_points
  reads) and recordings (every sweep of their PointCloud2 ``topic``, or
  every ``every``-th; recordings.py) as a dataset: split by file, by the
  lists ``ROOT/{train,val,test}.txt`` (paths relative to ROOT, one per
  line) where they exist, else by a seeded shuffle (FILE_SPLIT) of the files
  matching ``pattern`` under ROOT (the sweeps of one recording stay in one
  split)."""

  def __init__(self, pattern: str = '*', seed: int = 0, topic: str | None = None,
               every: int = 1):
    self.pattern, self.seed, self.topic, self.every = pattern, seed, topic, every

  def _all(self, root: str) -> list[str]:
    found = []
    for d, _, names in os.walk(root):
      for n in names:
        path = os.path.join(d, n)
        rel = os.path.relpath(path, root)
        if ((points.format_of(path) or recordings.format_of(path)) and
            (fnmatch.fnmatch(n, self.pattern) or
             fnmatch.fnmatch(rel, self.pattern))):
          found.append(path)
    return sorted(found)

  def nothing_found(self, root: str) -> str:
    """Why no file under ``root`` is a sweep to prepare: what the pattern
    matched and what the folder holds, by file name ending."""
    if any(os.path.isfile(os.path.join(root, f'{s}.txt')) for s in SPLITS):
      return (f'{root}: its split lists ({", ".join(f"{s}.txt" for s in SPLITS)}) name no '
              'file for the splits asked')
    ends = collections.Counter()
    for _, _, names in os.walk(root):
      ends.update(points.format_of(n) or recordings.format_of(n) or
                  os.path.splitext(n)[1] or '(no extension)' for n in names)
    held = (', '.join(f'{n} {e}' for e, n in ends.most_common(6)) +
            (', ...' if len(ends) > 6 else '')) if ends else 'no file at all'
    which = (f'match --pattern {self.pattern!r}' if self.pattern != '*' else
             'are point files or recordings')
    return (f'{root}: no files under it {which} (it holds {held}; point files end in '
            f'{", ".join(sorted(points.READERS))}, recordings in '
            f'{", ".join(recordings.RECORDING_FORMATS)})')

  def list_split(self, root: str, split: str) -> list[str]:
    lists = {s: os.path.join(root, f'{s}.txt') for s in SPLITS}
    if any(os.path.isfile(p) for p in lists.values()):
      if not os.path.isfile(lists[split]):
        return []
      with open(lists[split]) as f:
        paths = [os.path.join(root, line.strip()) for line in f if line.strip()]
      missing = [p for p in paths if not os.path.isfile(p)]
      if missing:
        raise DataError(f'{lists[split]}: {len(missing)} listed files do not exist, '
                        f'e.g. {missing[0]}')
      return paths
    files = self._all(root)
    order = np.random.default_rng(self.seed).permutation(len(files))
    bounds = np.cumsum([0] + [round(FILE_SPLIT[s] * len(files)) for s in SPLITS])
    bounds[-1] = len(files)
    i = SPLITS.index(split)
    return sorted(files[j] for j in order[bounds[i]:bounds[i + 1]])

  def count(self, path: str) -> int:
    """Scans of a file: its sweeps to keep for a recording, else 1. A
    recording that cannot be opened counts 1, the one failure reading it
    gives (:meth:`scans`)."""
    topic = None if recordings.format_of(path) == 'velodyne' else self.topic
    try:
      return recordings.count_sweeps(path, topic, self.every)
    except DataError:
      return 1

  def _sweeps(self, path: str, every: int):
    """A recording's recordings.Sweep, every ``every``-th; one that cannot
    be read on gives one more Sweep holding why."""
    topic = None if recordings.format_of(path) == 'velodyne' else self.topic
    try:
      yield from recordings.read_sweeps(path, topic, every)
    except DataError as e:
      yield recordings.Sweep(path, None, _error=str(e))

  def scans(self, paths):
    """The scans of ``paths`` one after another, for :meth:`load_scan`: a
    point file's path, or each kept recordings.Sweep of a recording."""
    for path in paths:
      if recordings.format_of(path):
        yield from self._sweeps(path, self.every)
      else:
        yield path

  def sample(self, paths, n: int):
    """Up to ``n`` scans spread over ``paths`` and over the sweeps of each
    recording (for the estimate), as :meth:`scans` gives them."""
    chosen = paths[:: max(1, len(paths) // n)][:n]
    per_file = -(-n // max(1, len(chosen)))
    for path in chosen:
      if recordings.format_of(path):
        stride = max(1, self.count(path) * self.every // per_file)
        yield from itertools.islice(self._sweeps(path, stride), per_file)
      else:
        yield path

  @staticmethod
  def load_scan(scan, sensor: SensorSpec, return_xyz: bool = False):
    """(H, W) depth[, (H, W, 3) xyz], :class:`unfolding.Unfolded` of a point
    file's path or a recordings.Sweep."""
    if isinstance(scan, recordings.Sweep):
      source, fields = scan.source, scan.fields
    else:
      source, fields = scan, points.read_points(scan)
    u = unfolding.unfold(fields, sensor, ring=points.ring_field(fields, source),
                         source=source)
    if u.off_elevation + u.out_of_range > REPORT_DROPPED * u.points:
      warnings.warn(f'{source}: {u.summary()}', stacklevel=2)
    return (u.depth, u.xyz, u) if return_xyz else (u.depth, u)


READERS = {'kitti': kitti, 'mpo': mpo, 'kitti360': kitti360, 'nuscenes': nuscenes,
           'files': Files()}
# The sensor preset a dataset is prepared with unless another is given.
DATASET_SENSOR = {'kitti': 'kitti', 'mpo': 'mpo', 'kitti360': kitti360.SENSOR,
                  'nuscenes': nuscenes.SENSOR}
MIN_VALID_FRACTION = 0.05  # a real scan returns on most of its pixels
MIN_RING_FRACTION = 0.25
# A scan on few of the spec's rows, those rows this full, is a sweep of a
# sensor of fewer beams than the spec (a random scatter fills a few pixels).
MIN_FULL_ROWS = 0.25


def junk_reason(depth, sensor: SensorSpec) -> str | None:
  """Why an unfolded scan is too sparse to train on, or None."""
  valid = np.asarray(codec.valid_depth(depth, sensor))
  frac = valid.mean()
  rings = int(valid.any(axis=1).sum())
  full = valid[valid.any(axis=1)].mean() if rings else 0.0
  if rings < MIN_RING_FRACTION * sensor.height and full >= MIN_FULL_ROWS:
    return (f'returns on only {rings} of the {sensor.height} rows of sensor '
            f'{sensor.name!r}, those {100 * full:.0f}% full: a sweep of {rings} beams, '
            f'not of the spec\'s {sensor.height}; is the spec the data\'s sensor?')
  if frac < MIN_VALID_FRACTION:
    return (f'only {valid.sum()} valid pixels ({100 * frac:.2f}% < '
            f'{100 * MIN_VALID_FRACTION:.0f}%): not a full LiDAR scan')
  if rings < MIN_RING_FRACTION * sensor.height:
    return f'returns on only {rings} of {sensor.height} rings'
  return None


def convert_split(paths, load, sensor: SensorSpec, target: str, angle_acc=None,
                  desc='scans', log=print, total: int | None = None):
  """Converts files into the (N, H, W) depth array ``target``, scan by scan
  (memory does not grow with N).

  ``paths``: the scans, each a file's path or a recordings.Sweep, that
  ``load`` unfolds; an iterator of ``total`` of them (default len(paths)).
  ``skipped`` lists (path, reason) for every scan that failed; ``foreign``
  how many of them are not sweeps of ``sensor`` (unfolding.NotThisSensor).
  With no scan, nothing is written (an old ``target`` is left for the caller
  to remove). Returns (N, skipped, foreign).
  """
  total = len(paths) if total is None else total
  skipped, foreign = [], 0
  writer = arrays.SplitWriter(target, total, sensor.shape)
  try:
    for scan in tqdm.tqdm(paths, desc=desc, unit='scan', file=sys.stderr, total=total,
                          disable=total < 2):
      path = getattr(scan, 'source', scan)
      try:
        with warnings.catch_warnings(record=True) as caught:
          warnings.simplefilter('always')
          depth, xyz, *_ = load(scan, sensor, return_xyz=True)
        for w in caught:
          log(f'warning: {w.message}')
      except (ValueError, OSError) as e:
        skipped.append((path, str(e)))
        foreign += isinstance(e, unfolding.NotThisSensor)
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
  return writer.close(), skipped, foreign


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


def estimate_sensor(paths, out: str, log=print, reader=None) -> SensorSpec:
  """``prepare --sensor auto``: a spec estimated from up to ESTIMATE_SWEEPS
  of ``paths`` (of a :class:`Files` ``reader``: of their sweeps, spread over
  each recording), printed with its fit and written to ``out/sensor.json``.
  A scan that cannot be read is skipped with one line, as the conversion
  skips it."""
  if not paths:
    raise DataError('--sensor auto: no training files to estimate the sensor from')
  reader = reader or Files()
  sweeps, read = [], []
  for scan in reader.sample(paths, ESTIMATE_SWEEPS):
    try:
      if isinstance(scan, recordings.Sweep):
        name, fields = scan.source, scan.fields
      else:
        name, fields = scan, points.read_points(scan)
    except (ValueError, OSError) as e:
      log(f'skipped: {e}')
      continue
    sweeps.append(fields)
    read.append(name)
  if not sweeps:
    raise DataError('--sensor auto: none of the training sweeps chosen to estimate the '
                    'sensor from could be read (see the reasons above)')
  fit = estimate.estimate(sweeps, sources=read,
                          name=os.path.basename(os.path.normpath(out)) or 'estimated')
  log(fit.summary())
  log(f'(from {len(read)} training sweeps; the spec is written to '
      f'{os.path.join(out, SENSOR_FILE)}: review it)')
  return fit.spec


def prepare(dataset: str, root: str, out: str, sensor: SensorSpec | None = None,
            splits=SPLITS, log=print, pattern: str = '*', split_seed: int = 0,
            topic: str | None = None, every: int = 1, auto_sensor: bool = False) -> dict:
  """Prepares every split of ``dataset`` under ``root`` into ``out``.

  ``sensor``: the SensorSpec to unfold with (the command resolves a name or
  a file, ``--sensor``); default the dataset's own preset (DATASET_SENSOR).
  ``auto_sensor``: one estimated from the training files instead
  (``--sensor auto``: :func:`estimate_sensor`). ``pattern``, ``split_seed``:
  which files of a ``files`` dataset, and how they split; ``topic``,
  ``every``: which PointCloud2 topic of its recordings, and every how many
  sweeps are kept (:class:`Files`).

  Every input is checked before anything is created. ``meta.json`` then
  describes every split array in ``out``: the ones written now, and those
  of an earlier run that this one leaves (``splits`` a subset), each with
  its identity (``identity``: size, shape, dtype, mtime, checksums;
  data/identity.py), which training checks; ``sensor.json`` the spec they
  were unfolded with.
  """
  if dataset not in READERS:
    raise ValueError(f'unknown dataset {dataset!r}; known: {sorted(READERS)}')
  unknown = [s for s in splits if s not in SPLITS]
  if unknown or not splits:
    raise ValueError(f'unknown splits {unknown}; known: {list(SPLITS)}')
  recordings.check_every(every)
  if dataset != 'files' and (topic is not None or every != 1):
    raise ValueError(f'topic and every are for recordings (dataset files), not {dataset}')
  if not os.path.isdir(root):
    raise FileNotFoundError(f'{root}: no such directory')
  reader = (Files(pattern, split_seed, topic, every) if dataset == 'files' else
            READERS[dataset])
  if sensor is not None:
    sensor_lib.check_spec(sensor)
    if auto_sensor:
      raise ValueError('prepare: give a sensor or auto_sensor=True, not both')
  if dataset == 'files' and not (sensor or auto_sensor):
    raise DataError('a folder of point files needs --sensor: a preset '
                    f'({", ".join(sorted(sensor_lib.PRESETS))}), a sensor spec '
                    'file, or auto (estimated from the files)')
  listed = {split: reader.list_split(root, split) for split in splits}
  if not any(listed.values()):
    if isinstance(reader, Files):
      raise FileNotFoundError(reader.nothing_found(root))
    raise FileNotFoundError(f'{root}: no {dataset} scan files for splits '
                            f'{list(splits)} (is this the dataset root?)')
  needs = {}  # a recording of each extra ([ros], [velodyne]), checked before anything is written
  for path in (p for ps in listed.values() for p in ps):
    kind = recordings.format_of(path)
    if kind:
      needs.setdefault(kind == 'velodyne', path)
  for path in needs.values():
    recordings.require(path)
  if auto_sensor:
    sensor = estimate_sensor(listed.get('train') or reader.list_split(root, 'train'),
                             out, log, reader if isinstance(reader, Files) else None)
  sensor = sensor or sensor_lib.PRESETS[DATASET_SENSOR[dataset]]
  kept = _kept_splits(out, splits, sensor)
  made = not os.path.exists(out)
  try:
    return _write(dataset, root, out, reader, listed, sensor, kept, log)
  except BaseException:
    if made:  # a folder this run made holds only what it wrote: nothing is left
      shutil.rmtree(out, ignore_errors=True)
    raise


def _write(dataset, root, out, reader, listed, sensor, kept, log) -> dict:
  """:func:`prepare`'s writing, once its inputs are checked. A run that
  prepares no scan changes nothing in ``out``: its old arrays, spec and
  meta.json stay as they were."""
  old = arrays.read_meta(out)
  os.makedirs(out, exist_ok=True)
  meta = {'dataset': dataset, 'sensor': sensor.name, 'shape': list(sensor.shape),
          'splits': dict(kept),
          'skipped': {s: old.get('skipped', {}).get(s, []) for s in kept}}
  acc = unfolding.AngleAccumulator(sensor)
  first_skip = None
  for split, paths in listed.items():
    scans, total = paths, len(paths)
    if isinstance(reader, Files):  # a recording is many scans
      scans, total = reader.scans(paths), sum(reader.count(p) for p in paths)
    count, skipped, foreign = convert_split(
        scans, reader.load_scan, sensor, arrays.split_path(out, split),
        angle_acc=acc if split == 'train' else None, desc=split, log=log, total=total)
    first_skip = first_skip or (skipped[0] if skipped else None)
    if not paths:
      log(f'{split}: no files found, split not written')
    meta['splits'][split] = int(count)
    meta['skipped'][split] = [{'path': p, 'reason': r} for p, r in skipped]
    log(f'{split}: {count} scans written, {len(skipped)} skipped' +
        (f' ({foreign} of another sensor than {sensor.name!r})' if foreign else ''))
  if not sum(meta['splits'][s] for s in listed):
    files = sum(len(p) for p in listed.values())
    path, reason = first_skip
    reason = reason if reason.startswith(path) else f'{path}: {reason}'
    raise DataError(f'{root}: every scan file was skipped, nothing prepared; the first '
                    f'of {files}: {reason}')
  sensor_lib.save(sensor, os.path.join(out, SENSOR_FILE))
  for split in listed:
    target = arrays.split_path(out, split)
    if not meta['splits'][split] and os.path.isfile(target):
      os.remove(target)  # a stale array from an earlier run must not be used
      log(f'{split}: removed the old {target} (this run found no scan for it)')
  angles = os.path.join(out, arrays.ANGLES)
  if acc.count.sum():
    arrays.save_array(angles, acc.result())
  elif 'train' in listed and os.path.isfile(angles):
    os.remove(angles)
    log(f'removed the old {angles} (no training scan to estimate it from)')
  # What each split array is, for training to check (identity.py).
  meta['identity'] = {split: identity.of_file(arrays.split_path(out, split), whole=True)
                   for split in SPLITS if os.path.isfile(arrays.split_path(out, split))}
  arrays.write_meta(out, meta)
  return meta
