"""DUSty-I on KITTI odometry (HDL-64E, 64x256); prepare the data first:

  python -m dusty_jax.tools.prepare --dataset kitti --root /path/to/kitti --out data/kitti
"""

from dusty_jax import configs


def get_config():
  c = configs.default()
  c.sensor.preset = 'kitti'
  c.data.name = 'kitti'
  c.data.dir = 'data/kitti'
  return c
