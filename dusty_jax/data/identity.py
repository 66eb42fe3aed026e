"""What a split file is, and whether it is still that file.

An identity is a JSON-ready dict: ``bytes`` (the file's size), ``shape`` and
``dtype`` (its header's), ``mtime_ns``, ``sample`` (SHA-256 of its header and
of SAMPLE_BLOCKS blocks spread over it; of all of it when small) and, where
all of the data was read, ``sha256`` (of the data after the header).
``prepare`` and the simulator write one per split into meta.json
(``identity``); a training records the one it trains on in its run directory
(pipeline.TrainingData) and compares it at each log step and at resume.

Two identities are the same data when size, shape, dtype and the checksums
both hold agree; the modification time only says when to look again (a
``touch`` changes nothing).
"""

from __future__ import annotations

import hashlib
import os
import time

import numpy as np

from dusty_jax.data import arrays

SAMPLE_BLOCKS = 64
BLOCK_BYTES = 1 << 16  # a 64x256 float32 scan; also what hashing reads at a time


def stat_key(path: str):
  """What a cheap look (one stat) sees of a file: size, mtime, inode, device."""
  st = os.stat(path)
  return st.st_size, st.st_mtime_ns, st.st_ino, st.st_dev


def _chunks(f):
  """The rest of file ``f``, BLOCK_BYTES at a time (memory stays flat)."""
  return iter(lambda: f.read(BLOCK_BYTES), b'')


def _sample(path: str, size: int) -> str:
  h = hashlib.sha256()
  with open(path, 'rb') as f:
    if size <= SAMPLE_BLOCKS * BLOCK_BYTES:
      for chunk in _chunks(f):
        h.update(chunk)
    else:
      for at in np.linspace(0, size - BLOCK_BYTES, SAMPLE_BLOCKS).astype(np.int64):
        f.seek(int(at))
        h.update(f.read(BLOCK_BYTES))
  return h.hexdigest()


def data_sha256(array: np.ndarray) -> str:
  """SHA-256 of an array's data as a C-ordered .npy file stores it."""
  return hashlib.sha256(memoryview(np.ascontiguousarray(array)).cast('B')).hexdigest()


def of_file(path: str, whole: bool = False, data: np.ndarray | None = None) -> dict:
  """The identity of the .npy file ``path``; with ``whole`` its ``sha256``
  too, from ``data`` (the file's array, already read) or by reading it."""
  shape, dtype, fortran, offset = arrays.npy_header(path)  # (a file cut short: its size)
  size, mtime, _, _ = stat_key(path)
  out = {'bytes': size, 'shape': list(shape), 'dtype': dtype.str, 'mtime_ns': mtime,
         'sample': _sample(path, size)}
  if whole and data is not None and not fortran:
    out['sha256'] = data_sha256(data)
  elif whole:
    h = hashlib.sha256()
    with open(path, 'rb') as f:
      f.seek(offset)
      for chunk in _chunks(f):
        h.update(chunk)
    out['sha256'] = h.hexdigest()
  return out


def when(ns) -> str:
  return time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(ns / 1e9))


def differences(old: dict, new: dict) -> list[str]:
  """What differs between two identities of a file, in words; [] when they
  are the same data."""
  out = []
  if old['bytes'] != new['bytes']:
    out.append(f"size {old['bytes']:,} -> {new['bytes']:,} bytes")
  if list(old['shape']) != list(new['shape']):
    out.append(f"shape {tuple(old['shape'])} -> {tuple(new['shape'])}")
  if np.dtype(old['dtype']) != np.dtype(new['dtype']):
    out.append(f"dtype {np.dtype(old['dtype'])} -> {np.dtype(new['dtype'])}")
  if not out:
    key = 'sha256' if 'sha256' in old and 'sha256' in new else 'sample'
    if old.get(key) != new.get(key):
      out.append('same size, other contents' + ('' if key == 'sha256' else
                                                 ' (in a sample of its blocks)'))
  if out and old.get('mtime_ns') != new.get('mtime_ns'):
    out.append(f"modified {when(new['mtime_ns'])}")
  return out

