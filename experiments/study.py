"""The study (benchmarks/study.py): a model trained on simulated HDL-64E
scans with a point-drop preset, at the CPU scale or the paper's.

    --config experiments/study.py:MODEL,PRESET,SCALE

MODEL: baseline | dusty1 | dusty2 (default dusty1); PRESET: a name of
dusty_jax.drops.PRESETS: authors (the paper's training, default), levels
(the same, drop levels fitted after it: sim-dusty1's), dips (sim-dusty2's);
SCALE: cpu (default) | paper. Parts left out or empty take their default:
`:dusty2` is DUSty-II, authors, cpu; `:dusty1,levels,paper` the shipped
DUSty-I's recipe at the paper's size.
"""

from dusty_jax import configs

DEFAULTS = ('dusty1', 'authors', 'cpu')  # MODEL, PRESET, SCALE


def get_config(arg: str = ''):
  parts = [p.strip() for p in arg.split(',')] if arg else []
  if len(parts) > len(DEFAULTS):
    raise configs.ConfigError(f'experiments/study.py:{arg}: give at most MODEL,PRESET,SCALE '
                              '(e.g. dusty1,levels,cpu)')
  return configs.study(*(p or d for p, d in zip(parts + [''] * 3, DEFAULTS)))
