"""Command-line tools: thin, they parse flags, call the library, print.

    python -m dusty_jax.tools.synthesize   simulate a dataset (data/synthetic.py)
    python -m dusty_jax.tools.prepare      KITTI / MPO folders -> prepared arrays
    python -m dusty_jax.tools.evaluate     Table II synthesis metrics of a run
    python -m dusty_jax.tools.invert       GAN inversion: reconstruct, restore, Table III
    python -m dusty_jax.tools.convert      an authors' .pth -> a run directory

Training stays ``python -m dusty_jax.train --config experiments/NAME.py``.
Every tool takes absl flags (``--name=value`` or ``--name value``;
booleans ``--name`` / ``--noname``), as train does. Each call parses into
its own ``flags.FlagValues``, so tools can be imported and called together
(tests call ``main([...])``).
"""

from __future__ import annotations

import sys

from absl import flags

# What a tool reports as a one-line error instead of a traceback.
USER_ERRORS = (ValueError, KeyError, FileNotFoundError, FileExistsError, ImportError)


def parse(values: flags.FlagValues, argv, doc: str) -> None:
  """Parses ``argv`` (without the program name; None: sys.argv) into
  ``values``; prints ``doc`` and the flags for --help."""
  args = list(sys.argv[1:] if argv is None else argv)
  if any(a in ('-h', '--help', '-help', '--helpfull') for a in args):
    print(doc.strip() + '\n\nflags:\n' + values.get_help())
    raise SystemExit(0)
  try:
    rest = values(['tool'] + args)
  except flags.Error as e:
    raise SystemExit(f'error: {e} (see --help)') from None
  if len(rest) > 1:
    raise SystemExit(f'error: unexpected arguments {rest[1:]} (see --help)')


def run(fn, *args):
  """Calls ``fn``; a user's mistake exits with ``error: ...``, one line."""
  try:
    return fn(*args)
  except USER_ERRORS as e:
    msg = e.args[0] if isinstance(e, KeyError) and e.args else e
    raise SystemExit(f'error: {msg}') from None
