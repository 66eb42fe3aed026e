"""dusty_jax: DUSty LiDAR scan synthesis as a functional JAX/Flax library.

Public API:
  load_checkpoint(path) -> (GeneratorParams, config) of a run directory, an exported
                           .npz or an authors' .pth (generator.py)
  load_pretrained(name) -> GeneratorParams shipped with the package
  sample(params, key, num) -> dict of inverse depth, measurability, mask, scan, points
  generate(params, z, key) -> the same dict for given latents z
  invert(params, scan, ...) -> latent search reconstruction
  render_drops(params, scan) -> realistic point-drops for a clean scan
  restore(params, depth, known) -> a damaged or sparse scan filled (restoration.py)
  enable_compilation_cache() -> JAX's persistent compilation cache on, for the whole
                           program, under ~/.cache/dusty_jax/xla (xla_cache.py): a new
                           process compiles invert's and sample's programs once. The
                           library's calls never switch it on; the command lines do.

Command lines: ``python -m dusty_jax.train`` and ``python -m dusty_jax.tools.NAME``.
"""

import importlib
from typing import TYPE_CHECKING

# Name -> the module that defines it. Loaded on first use (PEP 562), so that
# ``import dusty_jax`` and a command's --help do not pay for JAX, Flax and
# orbax (seconds on a small CPU) before anything needs them.
_API = {
    'GeneratorParams': ('dusty_jax.generator', 'GeneratorParams'),
    'SensorSpec': ('dusty_jax.sensor', 'SensorSpec'),
    'enable_compilation_cache': ('dusty_jax.xla_cache', 'enable'),
    'generate': ('dusty_jax.sampling', 'generate'),
    'get_sensor': ('dusty_jax.sensor', 'get_sensor'),
    'invert': ('dusty_jax.inversion', 'invert'),
    'load_checkpoint': ('dusty_jax.generator', 'load'),
    'load_pretrained': ('dusty_jax.pretrained', 'load_pretrained'),
    'render_drops': ('dusty_jax.inversion', 'render_drops'),
    'restore': ('dusty_jax.restoration', 'restore'),
    'sample': ('dusty_jax.sampling', 'sample'),
}

__all__ = sorted(_API)

if TYPE_CHECKING:  # what the names are, for readers and type checkers
  from dusty_jax.generator import GeneratorParams, load as load_checkpoint
  from dusty_jax.inversion import invert, render_drops
  from dusty_jax.pretrained import load_pretrained
  from dusty_jax.restoration import restore
  from dusty_jax.sampling import generate, sample
  from dusty_jax.sensor import SensorSpec, get_sensor
  from dusty_jax.xla_cache import enable as enable_compilation_cache


def __getattr__(name):
  if name not in _API:
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
  module, attr = _API[name]
  value = getattr(importlib.import_module(module), attr)
  globals()[name] = value  # once: later lookups do not come here
  return value


def __dir__():
  return sorted(set(globals()) | set(_API))
