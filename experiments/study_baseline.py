"""The study's the baseline on simulated HDL-64E scans (benchmarks/study.py).

`--config experiments/study_baseline.py` is the CPU scale; `...study_baseline.py:paper`
is the paper's network size and schedule.
"""

from dusty_jax import configs


def get_config(scale='cpu'):
  return configs.study('baseline', scale)
