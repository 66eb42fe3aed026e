"""Writing a file so that no reader ever sees half of it: :func:`atomic_write`,
and :func:`atomic_path` for writers that take a path rather than a file."""

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
