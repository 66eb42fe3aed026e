"""Prepared arrays: the on-disk format that training and evaluation read.

A prepared dataset is a directory holding, per split, ``{split}.npy``: metric
depth shaped (N, H, W), float32, 0 where there was no return (training reads
it into memory, or from the file batch by batch when it is large), plus
``angles.npy`` (2, H, W): the per-pixel elevation and azimuth estimated from
the training split, and ``meta.json`` (with each split file's identity:
data/identity.py). Simulated datasets add
the ground truth beside each split: ``{split}_complete.npy`` (the depth a
perfect sensor sees) and ``{split}_drop_prob.npy`` (the true probability of
each point-drop).
"""

from __future__ import annotations

import json
import os

import numpy as np

from dusty_jax import files, sensor as sensor_lib
from dusty_jax.errors import DataError
from dusty_jax.sensor import SensorSpec, check_angles

ANGLES = 'angles.npy'
META = 'meta.json'
SENSOR = 'sensor.json'  # the spec a prepared folder was unfolded with (prepare.py)


def split_path(directory: str, split: str, kind: str = '') -> str:
  return os.path.join(directory, f'{split}_{kind}.npy' if kind else f'{split}.npy')


# A training split up to this many MiB is read into memory (the default
# data's: 2,000 scans, 125 MiB), a larger one from its file batch by batch
# (FileRows); the default of config field data.memory_mb.
MEMORY_MB = 2048
# Value checks (check_values): a split with a smaller share of pixels inside
# the sensor's range holds no LiDAR scans (prepare refuses single scans below
# the same share); NaN and inf, which nothing of dusty_jax writes, count as
# drops up to MAX_NAN_SHARE of the pixels.
MIN_VALID_SHARE = 0.05
MAX_NAN_SHARE = 0.01
CHECK_SCANS = 512  # scans check_values reads of a split not held in memory


def _check_shape(path, shape, sensor, lead):
  want = sensor.shape
  if len(shape) != lead + 2 or tuple(shape[-2:]) != want:
    raise DataError(f'{path}: array of shape {tuple(shape)} does not match sensor '
                     f'{sensor.name!r} (expected (..., {want[0]}, {want[1]}))')


def npy_header(path: str):
  """(shape, dtype, fortran_order, offset of the data) of a .npy file, from
  its header; a file that is none is a DataError naming it."""
  try:
    with open(path, 'rb') as f:
      version = np.lib.format.read_magic(f)
      read = (np.lib.format.read_array_header_1_0 if version == (1, 0) else
              np.lib.format.read_array_header_2_0)
      shape, fortran, dtype = read(f)
      offset = f.tell()
  except ValueError as e:
    raise DataError(f'{path}: not a .npy array ({e})') from None
  if dtype.hasobject:
    raise DataError(f'{path}: holds Python objects ({dtype}), not numbers')
  return tuple(shape), dtype, fortran, offset


def npy_layout(path: str):
  """:func:`npy_header`, and a DataError naming the file and both sizes
  where its data is shorter than its header says (cut short, or being
  written)."""
  shape, dtype, fortran, offset = npy_header(path)
  want = offset + int(np.prod(shape)) * dtype.itemsize
  have = os.path.getsize(path)
  if have < want:
    raise DataError(f'{path}: {have:,} bytes where the {tuple(shape)} {dtype} of its '
                    f'header needs {want:,}: the file was cut short or is being written; '
                    'copy it again or prepare it again')
  return tuple(shape), dtype, fortran, offset


def _split_file(directory: str, split: str, kind: str) -> str:
  path = split_path(directory, split, kind)
  if not os.path.isfile(path):
    raise FileNotFoundError(
        f'{path}: no prepared {split!r} split here. Prepare real data with '
        '`python -m dusty_jax.tools.prepare --dataset kitti --root DIR --out DIR`, '
        'or simulate some with `python -m dusty_jax.tools.synthesize`.')
  return path


def _checked_layout(path, sensor):
  shape, dtype, fortran, offset = npy_layout(path)
  _check_shape(path, shape, sensor, lead=1)
  if shape[0] == 0:
    raise DataError(f'{path}: the split holds no scans')
  return shape, dtype, fortran, offset


def load_split(directory: str, split: str, sensor: SensorSpec,
               kind: str = '') -> np.ndarray:
  """Memory-mapped (N, H, W) array of a split, checked against the sensor
  and against its file's size (a file cut short is a DataError, not a map
  that dies of SIGBUS when read). Training reads with :func:`read_split`."""
  path = _split_file(directory, split, kind)
  _checked_layout(path, sensor)
  return np.load(path, mmap_mode='r')


def read_split(directory: str, split: str, sensor: SensorSpec,
               memory_bytes: int = MEMORY_MB << 20):
  """(N, H, W) scans of a split as training reads them: an array in memory
  when the file is at most ``memory_bytes``, else a :class:`FileRows`.
  Neither is touched by a later change to the file; either way a file cut
  short is a DataError naming it and its sizes."""
  path = _split_file(directory, split, '')
  shape, dtype, fortran, offset = _checked_layout(path, sensor)
  if os.path.getsize(path) > memory_bytes:
    if fortran:
      raise DataError(f'{path}: stored in Fortran order, which is read into memory '
                      f'only (above data.memory_mb here); save it C-ordered')
    return FileRows(path, shape, dtype, offset)
  count = int(np.prod(shape))
  with open(path, 'rb') as f:
    f.seek(offset)
    flat = np.fromfile(f, dtype=dtype, count=count)
  if flat.size < count:  # cut short since its header was read
    raise DataError(f'{path}: {offset + flat.nbytes:,} bytes where the {shape} {dtype} '
                    f'of its header needs {offset + count * dtype.itemsize:,}: the '
                    'file was cut short while it was read; copy or prepare it again')
  return flat.reshape(shape, order='F' if fortran else 'C')


class FileRows:
  """An (N, H, W) split too big for memory, read from its file scan by scan
  (``os.pread`` of the rows asked for) through a descriptor kept open: a
  file replaced by another (a rename, as prepare writes) keeps serving the
  old one, and a file cut short ends in a DataError naming it and its
  sizes, where a memory map would end the process with SIGBUS. Indexed by
  an integer, a slice or an array of indices, like the array it stands for.
  """

  def __init__(self, path: str, shape, dtype, offset: int):
    self.path, self.shape, self.dtype, self.offset = path, tuple(shape), np.dtype(dtype), offset
    self.ndim = len(self.shape)
    self.row_bytes = int(np.prod(self.shape[1:])) * self.dtype.itemsize
    self._fd = None
    self._fd = os.open(path, os.O_RDONLY)

  def __len__(self):
    return self.shape[0]

  def __getitem__(self, key):
    if isinstance(key, (int, np.integer)):
      return self[np.asarray([key])][0]
    if isinstance(key, slice):
      rows = np.arange(*key.indices(len(self)))
    else:
      rows = np.asarray(key)
      if rows.ndim != 1 or not np.issubdtype(rows.dtype, np.integer):
        raise TypeError(f'{self.path}: index rows with an int, a slice or a 1-D '
                        f'integer array, not {rows.dtype} of shape {rows.shape}')
    rows = np.where(rows < 0, rows + len(self), rows)
    if rows.size and (rows.min() < 0 or rows.max() >= len(self)):
      raise IndexError(f'{self.path}: row {rows[(rows < 0) | (rows >= len(self))][0]} '
                       f'out of range for {len(self)} scans')
    out = np.empty((rows.size,) + self.shape[1:], self.dtype)
    start = 0
    while start < rows.size:  # one read per run of consecutive rows
      end = start + 1
      while end < rows.size and rows[end] == rows[end - 1] + 1:
        end += 1
      want = (end - start) * self.row_bytes
      at = self.offset + int(rows[start]) * self.row_bytes
      data = os.pread(self._fd, want, at)
      if len(data) < want:
        have = os.fstat(self._fd).st_size
        raise DataError(
            f'{self.path}: cut short while training reads it: {have:,} bytes where '
            f'its {self.shape} {self.dtype} needs {self.offset + len(self) * self.row_bytes:,}; '
            'checkpoints saved before are intact: restore the file and rerun to resume')
      out[start:end] = np.frombuffer(data, self.dtype).reshape((end - start,) + self.shape[1:])
      start = end
    return out

  def close(self, _close=os.close):  # (bound here: still there at the interpreter's exit)
    fd, self._fd = self._fd, None
    if fd is not None:
      _close(fd)

  def __del__(self):
    self.close()


def check_values(depth, sensor: SensorSpec, path: str, log=print) -> dict:
  """Refuses a split that holds no LiDAR scans, in one line with the share
  found: more than MAX_NAN_SHARE of its pixels NaN or inf, fewer than
  MIN_VALID_SHARE inside the sensor's range (all drops, or depths far from
  it: another unit). NaN and inf below that share count as drops, and
  their number is logged. An array in memory is checked whole; a FileRows
  on CHECK_SCANS scans spread over it. Returns the shares found."""
  n = len(depth)
  sampled = not isinstance(depth, np.ndarray) and n > CHECK_SCANS
  scans = (depth if isinstance(depth, np.ndarray) else
           depth[np.linspace(0, n - 1, CHECK_SCANS).astype(int)] if sampled else depth[:])
  where = f' (in {CHECK_SCANS} of its {n} scans, spread over it)' if sampled else ''
  total = scans.size
  finite = np.isfinite(scans)
  nonfinite = total - int(np.count_nonzero(finite))
  valid = int(np.count_nonzero((scans > sensor.min_depth) & (scans < sensor.max_depth)))
  returns = finite & (scans != 0)
  shares = {'nonfinite': nonfinite / total, 'valid': valid / total,
            'returns': float(np.count_nonzero(returns)) / total}
  if shares['nonfinite'] > MAX_NAN_SHARE:
    raise DataError(
        f'{path}: {shares["nonfinite"]:.1%} of its pixels are NaN or inf{where}; at most '
        f'{MAX_NAN_SHARE:.0%} count as drops: write 0 where there is no return, as prepare '
        'does')
  if shares['valid'] < MIN_VALID_SHARE:
    if shares['returns'] < MIN_VALID_SHARE:
      raise DataError(
          f'{path}: {1 - shares["valid"]:.1%} of its pixels are drops{where} (0, NaN or '
          f'out of range; a LiDAR scan returns on most): no scans to train on')
    median = float(np.median(scans[returns]))
    raise DataError(
        f'{path}: only {shares["valid"]:.1%} of its pixels lie inside the sensor\'s range '
        f'({sensor.min_depth:g}, {sensor.max_depth:g}) m{where}; its returns\' median is '
        f'{median:.4g}: depths must be in metres')
  if nonfinite:
    log(f'{path}: {nonfinite:,} NaN or inf pixels ({shares["nonfinite"]:.3%}{where}) '
        'taken as drops')
  return shares


def check_sensor(directory: str, sensor: SensorSpec, named: str):
  """Refuses ``sensor`` (the config's, ``named`` says whence) where the
  prepared folder's sensor.json, the spec its data was unfolded with, differs
  in what the depths depend on (sensor.DATA_FIELDS): one DataError naming
  both and the first field that differs. A folder without one (simulated,
  or prepared before prepare wrote it) is not checked."""
  path = os.path.join(directory, SENSOR)
  if not os.path.isfile(path):
    return
  data = sensor_lib.load(path)
  diff = sensor_lib.first_difference(data, sensor, ('data', 'config'))
  if diff:
    columns = f' --config.sensor.width={data.width}' if data.width != sensor.width else ''
    raise DataError(f'{path}, the spec the data was prepared with, is not the config\'s '
                    f'({named}): {diff}; train with --config.sensor.file={path}{columns}')


def load_angles(directory: str, sensor: SensorSpec) -> np.ndarray:
  """(2, H, W) angle table of a prepared dataset (nominal if absent); a
  file that is not one is a DataError naming it."""
  path = os.path.join(directory, ANGLES)
  if not os.path.isfile(path):
    return sensor.nominal_angles()
  npy_layout(path)  # (a pickled array or a file cut short: named)
  try:
    arr = np.load(path, allow_pickle=False)
  except ValueError as e:
    raise DataError(f'{path}: not a .npy array of angles ({e})') from None
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
  with files.atomic_write(os.path.join(directory, META)) as f:
    json.dump(meta, f, indent=2, sort_keys=True)


def save_array(path: str, arr: np.ndarray):
  """Writes atomically: a half-written file never replaces a good one."""
  with files.atomic_write(path, 'wb') as f:
    np.save(f, np.ascontiguousarray(arr))


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
  written, cuts the file there and moves it into place atomically. (Its own
  os.replace, not files.atomic_write: the file lives across calls, is made
  by open_memmap, and a writer given no scan leaves none.)
  """

  def __init__(self, path: str, capacity: int, shape):
    self.path, self.tmp = path, path + '.tmp.npy'
    self.shape, self.count = tuple(shape), 0
    self.capacity = capacity
    try:
      self.offset = empty_array(self.tmp, (capacity,) + self.shape)
      self.file = open(self.tmp, 'r+b')
    except BaseException:  # (no memory or disk for the map): no file is left
      if os.path.exists(self.tmp):
        os.remove(self.tmp)
      raise
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
