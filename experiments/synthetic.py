"""DUSty-I on simulated HDL-64E scans: the default that runs anywhere.

The first run simulates the scenes (about a minute) and caches them.
"""

from dusty_jax import configs


def get_config():
  c = configs.default()
  c.sensor.preset = 'kitti'
  c.data.dir = ''
  c.data.num_synthetic = 2000
  return c
