"""Files whole or not at all: writing one so that no reader ever sees half of
it (:func:`atomic_write`, and :func:`atomic_path` for writers that take a
path rather than a file), and telling a folder's files from what they were
(:func:`sizes`, :func:`unlike`)."""

from __future__ import annotations

import contextlib
import os
import uuid

# Beside the file written: os.replace is atomic within one file system.
TMP_SUFFIX = '.tmp'


@contextlib.contextmanager
def atomic_path(path: str, suffix: str = ''):
  """Yields a temporary path beside ``path`` (ending in ``suffix``) for the
  caller to write, by any means (np.lib.format.open_memmap, other
  processes); on a clean exit moves that file onto ``path`` (os.replace),
  so a reader, or a run killed half-way, finds the old file or the new
  one, never a part of either. On an exception (Ctrl-C too) the temporary
  file is removed and ``path`` is left as it was. The temporary's name is
  this call's own: processes that write one file at once (those of a
  multi-process training) each move theirs into place whole."""
  tmp = f'{path}.{uuid.uuid4().hex}{TMP_SUFFIX}{suffix}'
  try:
    yield tmp
    os.replace(tmp, path)
  except BaseException:
    with contextlib.suppress(OSError):
      os.remove(tmp)
    raise


@contextlib.contextmanager
def atomic_write(path: str, mode: str = 'w'):
  """Opens a temporary file beside ``path`` for writing (``mode``: 'w' or
  'wb') and moves it onto ``path`` when it is written and closed, as
  :func:`atomic_path`: the old file or the new one, never a part of
  either. The folder must exist."""
  if mode not in ('w', 'wb'):
    raise ValueError(f"mode={mode!r}: atomic_write writes a whole file, 'w' or 'wb'")
  with atomic_path(path) as tmp, open(tmp, mode) as f:
    yield f


def sizes(folder: str, blocks: bool = False) -> dict:
  """{path inside ``folder``: bytes} of every file below it (``blocks``: as
  allocated on disk, which a copy of them needs)."""
  paths = [os.path.join(d, f) for d, _, fs in os.walk(folder) for f in fs]
  return {os.path.relpath(p, folder): os.stat(p).st_blocks * 512 if blocks
          else os.path.getsize(p) for p in paths}


def unlike(folder: str, saved: dict | None) -> str | None:
  """Why ``folder`` is not what :func:`sizes` recorded as ``saved``: no files,
  a file missing, truncated or of another size; None when nothing says so."""
  now = sizes(folder) if os.path.isdir(folder) else {}
  bad = sorted(n for n in saved or {} if now.get(n) != saved[n])
  if not now or not bad:
    return None if now else 'empty directory'
  name, more = bad[0], f', and {len(bad) - 1} more files' if len(bad) > 1 else ''
  if name not in now:
    return f'file missing: {name}{more}'
  what = 'truncated' if now[name] < saved[name] else 'damaged'
  return f'file {what}: {name} has {now[name]} bytes, {saved[name]} when saved{more}'
