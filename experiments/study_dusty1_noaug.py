"""The study's DUSty-I without DiffAugment (benchmarks/study.py): at the CPU
scale the discriminator cannot see point-drops through the augmentation and
DUSty-I's drops collapse; without it they do not (benchmarks/results/study.md).

`--config experiments/study_dusty1_noaug.py` is the CPU scale;
`...study_dusty1_noaug.py:paper` is the paper's network size and schedule.
"""

from dusty_jax import configs


def get_config(scale='cpu'):
  return configs.study('dusty1_noaug', scale)
