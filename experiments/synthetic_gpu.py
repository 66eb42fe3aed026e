"""DUSty-I on simulated HDL-64E scans at the paper's size and schedule (Table
I networks, batch 32, 781,250 steps as the authors train): for GPUs. On a
CPU a step of this model takes seconds; experiments/synthetic.py is the job
that finishes there.
"""

import os
import runpy

# The study's recipe, beside this file.
study = runpy.run_path(os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                    'study.py'))['study']


def get_config():
  c = study('dusty1', 'authors', 'paper')
  c.final_eval.num_synthesis = 1000
  c.final_eval.num_invert = 64
  return c
