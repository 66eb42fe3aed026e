"""DUSty-I on simulated HDL-64E scans at the paper's size and schedule (Table
I networks, batch 32, 781,250 steps as the authors train): for GPUs. On a
CPU a step of this model takes seconds; experiments/synthetic.py is the job
that finishes there.
"""

from dusty_jax import configs


def get_config():
  c = configs.study('dusty1', 'authors', 'paper')
  c.final_eval.num_synthesis = 1000
  c.final_eval.num_invert = 64
  return c
