"""DUSty-I on MPO sparse (HDL-32E, 32x256); prepare the data first:

  python -m dusty_jax.tools.prepare --dataset mpo --root /path/to/mpo --out data/mpo
"""

from dusty_jax import configs


def get_config():
  c = configs.default()
  c.sensor.preset = 'mpo'
  c.data.name = 'mpo'
  c.data.dir = 'data/mpo'
  return c
