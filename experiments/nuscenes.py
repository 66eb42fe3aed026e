"""DUSty-I on nuScenes' LIDAR_TOP sweeps (HDL-32E, 32x1024), on the split
RangeLDM reports on (data/nuscenes.py); prepare the data first:

  python -m dusty_jax.tools.prepare --dataset nuscenes --root /path/to/nuscenes --out data/nuscenes
"""

from dusty_jax import configs


def get_config():
  c = configs.default()
  c.sensor.preset = 'hdl32e'
  c.data.name = 'nuscenes'
  c.data.dir = 'data/nuscenes'
  return c
