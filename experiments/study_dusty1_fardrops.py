"""The study's DUSty-I with the peaks variant's options and each ring's share
of far returns held to the real scans' (configs.FAR_DROPS_VARIANT): G also
pays, with weight 100, for the squared gap per ring between the share of
its pixels that are returns beyond 40 m (judged on x_tilde, moved through
the keep values) and the real batch's. The peaks variant returns four times
the test scans' far returns, where its synthesis MMD gap lies
(benchmarks/far_returns.py; README "Where the MMD gap lives"). The ring x
depth rate term leaves its cells beyond 40 m to that term
(``drops.rate_skip_far``; README "The rate term's far cells"); its first
five seeds trained without, which ``--config.drops.rate_skip_far=False``
repeats.

`--config experiments/study_dusty1_fardrops.py` is the CPU scale; `...:paper`
the paper's network size and schedule.
"""

from dusty_jax import configs


def get_config(scale='cpu'):
  return configs.study('dusty1_fardrops', scale)
