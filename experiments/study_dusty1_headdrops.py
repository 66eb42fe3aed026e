"""The study's DUSty-I with drops by ring and range, the rate term training
the measurability head only (configs.HEAD_DROPS_VARIANT):
G matches the real keep rate per (ring, neighbours' depth) cell and has one
measurability offset per ring (benchmarks/study.py).

`--config experiments/study_dusty1_headdrops.py` is the CPU scale; `...:paper`
the paper's network size and schedule.
"""

from dusty_jax import configs


def get_config(scale='cpu'):
  return configs.study('dusty1_headdrops', scale)
