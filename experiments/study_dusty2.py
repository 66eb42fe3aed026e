"""The study's DUSty-II on simulated HDL-64E scans (benchmarks/study.py).

`--config experiments/study_dusty2.py` is the CPU scale; `...study_dusty2.py:paper`
is the paper's network size and schedule.
"""

from dusty_jax import configs


def get_config(scale='cpu'):
  return configs.study('dusty2', scale)
