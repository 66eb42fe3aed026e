"""DUSty-I on simulated HDL-64E scans: the main job, which finishes on a CPU.

The first run simulates the scenes (2,000 + 200 + 200 scans) and caches them:
24 CPU-seconds, 12.4 s on a 2-core AMD EPYC VM (load 1-3);
benchmarks/synthesize.py.
Then it trains the study's CPU-scale DUSty-I as the authors do for 2,500
steps, fits its drop levels per (ring, depth) cell to inversions of 256
training scans (dusty_jax.levels: the recipe of the shipped `sim-dusty1`,
drops preset 'levels') and ends with a
short evaluation on the test split (final_evaluation.json / .png: Table II
on 200 scans, drop placement of 32 inverted scans against the simulator's
truth). The paper-size model and schedule, for GPUs: experiments/synthetic_gpu.py.
"""

import os
import runpy

# The study's recipe, beside this file.
study = runpy.run_path(os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                    'study.py'))['study']

PRESET = 'levels'  # sim-dusty1's recipe: the authors' training, then drop levels


def get_config():
  c = study('dusty1', PRESET, 'cpu')
  c.final_eval.num_synthesis = 200
  c.final_eval.num_invert = 32
  return c
