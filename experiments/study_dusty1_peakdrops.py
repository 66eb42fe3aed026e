"""The study's DUSty-I with the mask detached, its dips filled and its peaks
held to the real scans' (configs.PEAK_DROPS_VARIANT): the dips variant
(study_dusty1_dipdrops.py) whose G also pays, with weight 10, for how far
the mean height of the returned pixels in front of both ring neighbours
exceeds the real batch's, the lattice of near pixels that the dips variant
leaves (benchmarks/study.py; README "Depth that survives the drops").

`--config experiments/study_dusty1_peakdrops.py` is the CPU scale; `...:paper`
the paper's network size and schedule.
"""

from dusty_jax import configs


def get_config(scale='cpu'):
  return configs.study('dusty1_peakdrops', scale)
