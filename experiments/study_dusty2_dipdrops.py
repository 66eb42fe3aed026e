"""The study's DUSty-II with the mask detached and its dips filled
(configs.DIP_DROPS_VARIANT; study_dusty1_dipdrops.py for DUSty-I):
does the variant carry over (benchmarks/study.py; README "Depth that
survives the drops")?

`--config experiments/study_dusty2_dipdrops.py` is the CPU scale; `...:paper`
the paper's network size and schedule.
"""

from dusty_jax import configs


def get_config(scale='cpu'):
  return configs.study('dusty2_dipdrops', scale)
