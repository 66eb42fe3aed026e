"""DUSty-I on the simulated default data (HDL-64E, 64 x 256): the main job's
recipe at the size benchmarks/scaling.py names for it, channels 32..256 and
latent 128 (benchmarks/README.md, section scaling). It takes 2.9x the main
job's step time (0.54 against 0.19 s on 2 CPU cores) for a model whose
samples match the scans better (validation MMD) and whose restoration is no
worse.
"""

import os
import runpy

# The main job's recipe, beside this file.
synthetic = runpy.run_path(os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                        'synthetic.py'))


def get_config():
  c = synthetic['get_config']()
  c.ch_base, c.ch_max, c.latent_dim = 32, 256, 128
  return c
