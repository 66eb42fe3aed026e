"""The point-drop variants the study trained on the way to the shipped
presets (dusty_jax.drops.PRESETS), as data.

Each entry is the ``drops`` options a variant adds to configs.study's
model (the suffix of its run name: ``dusty1_fardrops`` is DUSty-I with
LINEAGE['fardrops']); each adds to the one before it, except the first.
'dipdrops' is the library's preset 'dips'; 'fardrops' was its preset 'far'
until 2026-11-26; the others lost on the study's figures (README.md in this
folder). Options that left the library (configs.REMOVED_DROPS) train only at
the commit configs.LAST_WITH names (f597033, whose experiments/study_*.py
files and configs.STUDY_DROPS built these configs; ca3bdad for the peak and
far terms). 'noaug' is DUSty-I without DiffAugment, a diagnosis run.

    from lineage import config
    c = config('dusty1_detdrops')  # configs.study('dusty1') + LINEAGE['detdrops']
"""

from __future__ import annotations

from dusty_jax import configs

# The shipped DUSty-I of the first screens (sim-dusty1-channel): D sees the
# keep-mask as a noised channel hidden half the time, G matches the real
# keep rate, the measurability starts at the data's keep rate (logit(0.8)).
DROPS = dict(mask_channel=1.0, mask_noise=0.1, mask_dropout=0.5, rate_weight=10.0,
             mask_bias=1.386)
# Drops by ring and range: G matches the real keep rate of each (ring,
# neighbours' depth) cell; one learned measurability offset per ring.
RANGE = dict(rate_weight=100.0, mask_bias=1.386, ring_bias=True)
# The rate term trains only the measurability head.
HEAD = dict(RANGE, rate_head_only=True)
# No gradient of the mask reaches the trunk (sim-dusty1-detached).
DETACHED = dict(HEAD, mask_detached=True)
# G fills the dips among its returns (sim-dusty1-dips; drops.PRESETS['dips']).
DIP = dict(DETACHED, dip_weight=10.0)
# G pays for peaks beyond the real scans' (sim-dusty1-peaks).
PEAK = dict(DIP, peak_weight=10.0)
# Each ring's share of far returns held to the real batch's, the rate
# term's far cells left to it (sim-dusty1 until 2026-11-26; left the library after ca3bdad).
FAR = dict(PEAK, far_weight=100.0, rate_skip_far=True)

# Run-name suffix -> the options it adds.
LINEAGE = {'drops': DROPS, 'rangedrops': RANGE, 'headdrops': HEAD, 'detdrops': DETACHED,
           'dipdrops': DIP, 'peakdrops': PEAK, 'fardrops': FAR}


def config(run: str, scale: str = 'cpu'):
  """The study config of a lineage run name (``dusty1``, ``dusty2_dipdrops``,
  ``dusty1_noaug``, ...); ConfigError if it needs an option that left the
  library."""
  model, _, suffix = run.partition('_')
  c = configs.study(model, 'authors', scale)
  if suffix == 'noaug':
    c.augment = ''
  elif suffix:
    if suffix not in LINEAGE:
      raise configs.ConfigError(f'unknown lineage run {run!r}; known suffixes: noaug, '
                                f'{", ".join(LINEAGE)}')
    c.drops.update(LINEAGE[suffix])
  return configs.upgrade(c)  # refuses the removed options (configs.LAST_WITH has them)
