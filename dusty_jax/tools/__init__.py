"""Command-line tools: thin, they parse flags, call the library, print.

    python -m dusty_jax.tools.synthesize   simulate a dataset (data/synthetic.py)
    python -m dusty_jax.tools.prepare      KITTI / MPO folders -> prepared arrays
    python -m dusty_jax.tools.evaluate     Table II synthesis metrics of a run
    python -m dusty_jax.tools.invert       GAN inversion: reconstruct, restore, Table III
    python -m dusty_jax.tools.convert      an authors' .pth -> a run directory
    python -m dusty_jax.tools.train_encoder  the encoder that starts inversion (encoder.py)

Training stays ``python -m dusty_jax.train --config experiments/NAME.py``.
Every tool takes absl flags (``--name=value`` or ``--name value``;
booleans ``--name`` / ``--noname``), as train does. Each call parses into
its own ``flags.FlagValues``, so tools can be imported and called together
(tests call ``main([...])``).
"""

from __future__ import annotations

import sys

from absl import flags

from dusty_jax import cli
from dusty_jax.cli import run  # noqa: F401  (the one place errors become a line)


def parse(values: flags.FlagValues, argv, doc: str) -> None:
  """Parses ``argv`` (without the program name; None: sys.argv) into
  ``values``; prints ``doc`` and the flags for --help. A bad flag is one
  line and exit 2."""
  args = list(sys.argv[1:] if argv is None else argv)
  if any(a in ('-h', '--help', '-help', '--helpfull') for a in args):
    print(doc.strip() + '\n\nflags:\n' + values.get_help())
    raise SystemExit(0)
  rest = cli.parse_flags(['tool'] + args, values, config=None)
  if len(rest) > 1:
    cli.fail(f'unexpected arguments {rest[1:]} (see --help)', cli.USAGE)
