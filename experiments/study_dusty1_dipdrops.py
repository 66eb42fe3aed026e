"""The study's DUSty-I with the mask detached and its dips filled
(configs.DIP_DROPS_VARIANT): the mask-detached variant
(study_dusty1_detdrops.py) whose G also pays, with weight 10, for the depth
of each returned pixel that lies behind both ring neighbours, the far
speckle that cost that variant its depth at other training seeds
(benchmarks/study.py; README "Depth that survives the drops").

`--config experiments/study_dusty1_dipdrops.py` is the CPU scale; `...:paper`
the paper's network size and schedule.
"""

from dusty_jax import configs


def get_config(scale='cpu'):
  return configs.study('dusty1_dipdrops', scale)
