"""JAX's persistent compilation cache, under the dusty_jax cache directory.

Compiling the inversion's search or a sampler takes seconds on a CPU, each
time a process starts. :func:`enable` turns JAX's own persistent cache on,
through ``jax.config``, for the whole process, so that a second process
making the same call loads the compiled program from
``$DUSTY_JAX_CACHE/xla`` (default ``~/.cache/dusty_jax/xla``) instead of
compiling it again. A program switches it on where it starts: the command
lines do (cli.run, which train and every tool go through), and a library
user's program calls ``dusty_jax.enable_compilation_cache()``. The
library's own calls (invert, sample, load_pretrained, ...) never do: they
leave a caller's JAX settings as they were.

``DUSTY_JAX_COMPILATION_CACHE=0`` (or ``off``, ``false``, ``no``) leaves
JAX's cache alone. A cache directory the user configured for JAX
(``JAX_COMPILATION_CACHE_DIR`` or ``jax.config.update``) is theirs: it is
used as it is, and so is a minimum compile time they set; JAX's own
``jax_enable_compilation_cache`` still turns every cache off.

In the directory dusty_jax chose, once per process:
  * an entry JAX cannot read (cut short, overwritten) is deleted, with one
    line, so that JAX compiles the program and writes it again (JAX itself
    warns on every run and never replaces it). Each entry is checked once,
    by the first process that starts after it was written; one that is
    unreadable and only just written is read again after SETTLE_S, as JAX
    writes an entry in one call: unchanged and still unreadable then, it is
    damaged, not being written;
  * a directory that cannot be written gives one line; the programs found
    there are used and new ones are compiled without being written.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
import time
import zlib

import jax

from dusty_jax.data import pipeline

try:  # JAX compresses entries with zstd where it can (zstandard, or Python 3.14's
  from compression import zstd  # compression.zstd), else with zlib.
except ImportError:
  zstd = None
try:
  import zstandard
except ImportError:
  zstandard = None

ENV = 'DUSTY_JAX_COMPILATION_CACHE'
OFF = ('0', 'off', 'false', 'no')
# Programs compiling in less than this are not written (JAX's default is 1 s).
# The inversion's search and the samplers take seconds to minutes; the
# encoder's start under a second on a quiet 2-core CPU.
MIN_COMPILE_SECS = 0.2
_JAX_DEFAULT_MIN_SECS = 1.0
ENTRY_SUFFIX = '-cache'  # JAX's name for an entry's file (its '-atime' files beside)
CHECKED = '.dusty_jax_checked'  # its modification time: entries older are checked
# JAX writes an entry with one write call (lru_cache.LRUCache.put): one that
# is unreadable and unchanged for this long is damaged, not being written.
SETTLE_S = 0.5
# Entries changed this long before a check began are checked again by the
# next (file times may be this coarse).
MTIME_GRAIN_S = 2.0
# No compiled program is this large: JAX writes none (a read-only cache).
NEVER_WRITE_BYTES = 2**62

log = logging.getLogger(__name__)
_state = {'done': False, 'directory': None}


def directory() -> str:
  """Where dusty_jax keeps compiled programs when the user named none: under
  the cache of the simulated data (``$DUSTY_JAX_CACHE``, default
  ``~/.cache/dusty_jax``)."""
  return os.path.join(pipeline.default_cache(), 'xla')


def enable() -> str | None:
  """Turns JAX's persistent compilation cache on for the whole process (once;
  cheap after the first call): ``dusty_jax.enable_compilation_cache()``.

  Sets ``jax.config``'s ``jax_compilation_cache_dir`` to
  ``$DUSTY_JAX_CACHE/xla`` (``~/.cache/dusty_jax/xla``) and, where it is
  still JAX's default, ``jax_persistent_cache_min_compile_time_secs`` to
  MIN_COMPILE_SECS; a cache directory the program set already is kept, and
  ``DUSTY_JAX_COMPILATION_CACHE=0`` changes nothing. Returns the directory
  in use, or None when the cache is off.
  """
  if _state['done']:
    return _state['directory']
  _state['done'] = True
  if os.environ.get(ENV, '').strip().lower() in OFF:
    return None
  own = jax.config.jax_compilation_cache_dir
  if own:  # the user's own cache: theirs to configure.
    _state['directory'] = own
    return own
  path = directory()
  try:
    os.makedirs(path, exist_ok=True)
  except OSError as e:
    log.warning(f'the compilation cache {path} cannot be made ({e.strerror}): programs '
                f'are compiled in each process; set DUSTY_JAX_CACHE to a folder you can '
                f'write, or {ENV}=0')
    return None
  jax.config.update('jax_compilation_cache_dir', path)
  if ('JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS' not in os.environ and
      jax.config.jax_persistent_cache_min_compile_time_secs == _JAX_DEFAULT_MIN_SECS):
    jax.config.update('jax_persistent_cache_min_compile_time_secs', MIN_COMPILE_SECS)
  removed = remove_damaged(path)
  if removed is None:
    jax.config.update('jax_persistent_cache_min_entry_size_bytes', NEVER_WRITE_BYTES)
    log.warning(f'the compilation cache {path} cannot be written: programs found there '
                f'are used, new ones are compiled in each process; make it writable, '
                f'or set DUSTY_JAX_CACHE to a folder you can write')
  elif removed:
    what = 'entry' if len(removed) == 1 else 'entries'
    log.warning(f'removed {len(removed)} damaged {what} of the compilation cache {path} '
                f'(JAX could not read them); their programs are compiled and written again')
  _state['directory'] = path
  return path


def readable(data: bytes) -> bool:
  """Whether ``data`` is an entry JAX can read: one compressed stream
  (zstd or zlib, as JAX writes them) of more than its 8-byte header."""
  for decompress in (zstd and zstd.decompress,
                     zstandard and zstandard.ZstdDecompressor().decompress, zlib.decompress):
    if decompress:
      try:
        return len(decompress(data)) > 8
      except Exception:  # each library has its own error type; the next may read it
        continue
  return False


def remove_damaged(path: str) -> list[str] | None:
  """Deletes the entries under ``path`` that JAX could not read, among those
  changed since the last check (one just written: once it is SETTLE_S old
  and unchanged); returns their file names, or None where ``path`` cannot
  be written (nothing is checked then: nothing could be repaired)."""
  stamp = os.path.join(path, CHECKED)
  try:
    fd, fresh = tempfile.mkstemp(dir=path, prefix=CHECKED)
    os.close(fd)
  except OSError:
    return None
  try:
    since = os.stat(stamp).st_mtime
  except OSError:  # never checked
    since = 0.0
  start = time.time()
  removed, young = [], []
  for entry in os.scandir(path):
    try:
      if not entry.name.endswith(ENTRY_SUFFIX):
        continue
      st = entry.stat()
      if st.st_mtime < since or _readable_file(entry.path):
        continue
      if start - st.st_mtime < SETTLE_S:  # maybe being written: read again below
        young.append((entry, (st.st_size, st.st_mtime_ns)))
        continue
      _remove(entry.path)
      removed.append(entry.name)
    except OSError:  # gone meanwhile (evicted by another process)
      continue
  if young:
    time.sleep(SETTLE_S)
    for entry, before in young:
      try:
        st = os.stat(entry.path)
        if (st.st_size, st.st_mtime_ns) == before and not _readable_file(entry.path):
          _remove(entry.path)
          removed.append(entry.name)
      except OSError:
        continue
  until = start - MTIME_GRAIN_S
  # (Not files.atomic_write: the file moved onto the stamp is the probe made
  # above, and all it carries is its modification time.)
  try:
    os.utime(fresh, (until, until))
    os.replace(fresh, stamp)
  except OSError:  # made read-only meanwhile: checked again next time
    with contextlib.suppress(OSError):
      os.remove(fresh)
  return removed


def _readable_file(path: str) -> bool:
  with open(path, 'rb') as f:
    return readable(f.read())


def _remove(path: str):
  """Deletes an entry and its access-time file (JAX's, where it keeps one)."""
  os.remove(path)
  with contextlib.suppress(OSError):
    os.remove(path[:-len(ENTRY_SUFFIX)] + '-atime')
