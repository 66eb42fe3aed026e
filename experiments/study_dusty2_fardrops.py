"""The study's DUSty-II with the far-returns variant (configs.FAR_DROPS_VARIANT;
study_dusty1_fardrops.py for DUSty-I): does the variant carry over
(benchmarks/study.py; README "The rate term's far cells")?

`--config experiments/study_dusty2_fardrops.py` is the CPU scale; `...:paper`
the paper's network size and schedule.
"""

from dusty_jax import configs


def get_config(scale='cpu'):
  return configs.study('dusty2_fardrops', scale)
