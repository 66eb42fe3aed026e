"""The study's DUSty-II with drops by ring and range and the mask detached from
the trunk (configs.DETACHED_DROPS_VARIANT, as study_dusty1_detdrops.py for
DUSty-I): README "Point-drops that survive training", benchmarks/study.py.

`--config experiments/study_dusty2_detdrops.py` is the CPU scale; `...:paper`
the paper's network size and schedule.
"""

from dusty_jax import configs


def get_config(scale='cpu'):
  return configs.study('dusty2_detdrops', scale)
