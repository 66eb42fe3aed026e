"""DUSty-I on simulated VLP-16 scans (16 x 256): the main job's recipe at the
size benchmarks/scaling.py names for a 16-ring sensor, channels 32..256 and
latent 128 (restoration of its scans improved with each width tried; no
smaller size came within the seed spread of this one: benchmarks/README.md,
section scaling).
"""

import os
import runpy

# The main job's recipe, beside this file.
synthetic = runpy.run_path(os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                        'synthetic.py'))


def get_config():
  c = synthetic['get_config']()
  c.sensor.preset, c.sensor.width = 'vlp16', 256
  c.ch_base, c.ch_max, c.latent_dim = 32, 256, 128
  return c
