"""DUSty-I on KITTI-360 (HDL-64E, 64x1024), on the split LiDARGen and R2DM
report on (data/kitti360.py); prepare the data first:

  python -m dusty_jax.tools.prepare --dataset kitti360 --root /path/to/KITTI-360 --out data/kitti360
"""

from dusty_jax import configs


def get_config():
  c = configs.default()
  c.sensor.preset = 'hdl64e'
  c.data.name = 'kitti360'
  c.data.dir = 'data/kitti360'
  return c
