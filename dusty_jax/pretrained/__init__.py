"""Small trained generators shipped with the package, loadable offline.

    params = dusty_jax.load_pretrained('sim-dusty1')
    rec = dusty_jax.invert(params, scan, num_steps=300)

Each is one ``NAME.npz`` in this folder (numpy arrays only: loading runs no
code): the EMA generator's variables under ``variables/...``, the angle
table, and ``meta``, a JSON string of the sensor, the model settings, the
tolerance and where the weights came from (generator.export writes them).
They were trained on simulated HDL-64E scenes, not on real data: by
``benchmarks/study.py`` (see benchmarks/results/study.md), and sim-dusty1 by
the main command (experiments/synthetic.py) and its encoder. Each file's
``source`` says which; sim-dusty1's and sim-dusty2's also carry a
``training`` record (config, drops options, encoder options).
"""

from __future__ import annotations

import os

from dusty_jax import generator

HERE = os.path.dirname(os.path.abspath(__file__))


def available() -> list[str]:
  return sorted(f[:-4] for f in os.listdir(HERE) if f.endswith('.npz'))


def path_of(name: str) -> str:
  return os.path.join(HERE, f'{name}.npz')


def load_pretrained(name: str):
  """The shipped generator ``name`` as a GeneratorParams (see ``available()``)."""
  path = path_of(name)
  if not os.path.isfile(path):
    raise ValueError(f'no pretrained model {name!r}; available: {available()}')
  return generator.load_file(path)


def with_encoder() -> list[str]:
  """The shipped models that carry an encoder (invert(init='encoder'))."""
  return [n for n in available() if 'encoder' in generator.read_meta(path_of(n))]


def describe(name: str) -> dict:
  """What the shipped ``name`` says of itself: sensor, model settings,
  tolerance, source and, for sim-dusty1 and sim-dusty2, how it was trained
  (``training``: the experiments/ config that trains it, its drops options,
  ...)."""
  if not os.path.isfile(path_of(name)):
    raise ValueError(f'no pretrained model {name!r}; available: {available()}')
  return generator.read_meta(path_of(name))


def export(params, name: str, source: str = '', directory: str = HERE,
           training: dict | None = None) -> str:
  """Writes a GeneratorParams as ``NAME.npz`` (in this package by default);
  returns the path."""
  return generator.export(params, os.path.join(directory, f'{name}.npz'), source,
                          training)
