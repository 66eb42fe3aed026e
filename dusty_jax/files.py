"""Writing a file so that no reader ever sees half of it: :func:`atomic_write`."""

from __future__ import annotations

import contextlib
import os

# Beside the file written: os.replace is atomic within one file system.
TMP_SUFFIX = '.tmp'


@contextlib.contextmanager
def atomic_write(path: str, mode: str = 'w'):
  """Opens ``path + '.tmp'`` for writing (``mode``: 'w' or 'wb'); on a clean
  exit moves it onto ``path`` (os.replace), so a reader, or a run killed
  half-way, finds the old file or the new one, never a part of either. On an
  exception (Ctrl-C too) the temporary file is removed and ``path`` is left
  as it was. The folder must exist."""
  if mode not in ('w', 'wb'):
    raise ValueError(f"mode={mode!r}: atomic_write writes a whole file, 'w' or 'wb'")
  tmp = path + TMP_SUFFIX
  try:
    with open(tmp, mode) as f:
      yield f
    os.replace(tmp, path)
  except BaseException:
    with contextlib.suppress(OSError):
      os.remove(tmp)
    raise
