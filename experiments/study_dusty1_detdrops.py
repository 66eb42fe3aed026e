"""The study's DUSty-I with drops by ring and range and the mask detached from
the trunk (configs.DETACHED_DROPS_VARIANT): G matches the real keep rate per
(ring, neighbours' depth) cell on its measurability head, has one
measurability offset per ring, and no gradient of the mask reaches G's
shared trunk, which learns from x_tilde alone (benchmarks/study.py).

`--config experiments/study_dusty1_detdrops.py` is the CPU scale; `...:paper`
the paper's network size and schedule.
"""

from dusty_jax import configs


def get_config(scale='cpu'):
  return configs.study('dusty1_detdrops', scale)
