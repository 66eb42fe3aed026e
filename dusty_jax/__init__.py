"""dusty_jax: DUSty LiDAR scan synthesis as a functional JAX/Flax library.

Public API:
  load_checkpoint(path) -> (GeneratorParams, config) of a run directory, an exported
                           .npz or an authors' .pth (generator.py)
  load_pretrained(name) -> GeneratorParams shipped with the package
  sample(params, key, num) -> dict of inverse depth, measurability, mask, scan, points
  generate(params, z, key) -> the same dict for given latents z
  invert(params, scan, ...) -> latent search reconstruction
  render_drops(params, scan) -> realistic point-drops for a clean scan

Command lines: ``python -m dusty_jax.train`` and ``python -m dusty_jax.tools.NAME``.
"""

from dusty_jax.generator import GeneratorParams, load as load_checkpoint
from dusty_jax.inversion import invert, render_drops
from dusty_jax.pretrained import load_pretrained
from dusty_jax.sampling import generate, sample
from dusty_jax.sensor import SensorSpec, get_sensor

__all__ = ['GeneratorParams', 'SensorSpec', 'generate', 'get_sensor', 'invert',
           'load_checkpoint', 'load_pretrained', 'render_drops', 'sample']
