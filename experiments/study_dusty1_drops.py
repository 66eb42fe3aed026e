"""The study's DUSty-I with the point-drop variant (configs.DROPS_VARIANT):
drops that survive training at the CPU scale (benchmarks/study.py).

`--config experiments/study_dusty1_drops.py` is the CPU scale; `...:paper` the
paper's network size and schedule.
"""

from dusty_jax import configs


def get_config(scale='cpu'):
  return configs.study('dusty1_drops', scale)
