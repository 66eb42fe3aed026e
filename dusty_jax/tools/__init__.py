"""Command-line tools: thin, they parse flags, call the library, print.

    python -m dusty_jax.tools.synthesize   simulate a dataset (data/synthetic.py)
    python -m dusty_jax.tools.prepare      datasets, point files, ROS bags -> prepared arrays
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

import importlib.util
import os
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


def valid_corruption(spec: str, removing: bool = False) -> bool:
  """--corrupt's validator: a bad spec (with ``removing``, also one that
  removes no pixel) is a bad flag (exit 2)."""
  if spec:
    from dusty_jax import corrupt  # JAX: only for a given --corrupt
    try:
      removes = corrupt.removes(spec)  # (parses it: a bad spec raises)
      if removing and not removes:
        raise ValueError(f'corruption {spec!r} removes no pixel; give drop:F or beams:K')
    except ValueError as e:
      raise flags.ValidationError(str(e)) from None
  return True


def pretrained_names() -> list[str]:
  """The models dusty_jax/pretrained ships, read from the folder without
  importing it (which loads JAX), so that --help can name them."""
  spec = importlib.util.find_spec('dusty_jax.pretrained')
  folder = list(spec.submodule_search_locations)[0]
  return sorted(f[:-4] for f in os.listdir(folder) if f.endswith('.npz'))


MODEL_FORMS = ("a training run directory, a pretrained model's name ({names}), a "
               "generator .npz (generator.export) or an authors' .pth")


def model_help(what: str = 'the generator') -> str:
  """A --workdir flag's help: the forms :func:`load_model` accepts."""
  return f'{what}: ' + MODEL_FORMS.format(names=', '.join(pretrained_names()))


def load_model(source: str):
  """(GeneratorParams, config or None) of ``source``: a path that exists
  (run directory, .npz, .pth: load_checkpoint), else a pretrained name
  (load_pretrained; config None)."""
  # The library (and JAX) load once the flags are good.
  from dusty_jax import generator, pretrained
  if os.path.exists(source) or source not in pretrained_names():
    if not os.path.exists(source):
      raise FileNotFoundError(
          f'{source}: no such run directory or file, nor a pretrained model; give '
          + MODEL_FORMS.format(names=', '.join(pretrained_names())))
    return generator.load(source)
  return pretrained.load_pretrained(source), None
