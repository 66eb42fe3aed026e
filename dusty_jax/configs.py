"""Shared defaults for every experiment; experiments/*.py override a few.

The defaults train as the authors' code (kazuto1011/dusty-gan) does; every
deviation we prefer is an option here (README: "Differences from the
authors' code").
"""

import json
import os

import ml_collections

FILE = 'config.json'  # a run's config, in its directory


def default() -> ml_collections.ConfigDict:
  c = ml_collections.ConfigDict()
  c.seed = 0
  c.model = 'dusty1'             # baseline | dusty1 | dusty2

  c.sensor = ml_collections.ConfigDict()
  c.sensor.preset = 'kitti'      # kitti (HDL-64E 64x256) | mpo (HDL-32E 32x256)
  c.sensor.height = 0            # with preset '', a tiny sensor of this size
  c.sensor.width = 0             # 0: the preset's width

  c.data = ml_collections.ConfigDict()
  c.data.name = ''               # kitti | mpo, for messages
  c.data.dir = ''                # prepared arrays; '' = simulated scenes
  c.data.num_synthetic = 2000    # simulated training scans (default data)
  c.data.seed = 0
  c.data.cache = ''              # '' = ~/.cache/dusty_jax

  # Networks (the paper's Table I).
  c.latent_dim = 512
  c.ch_base = 64
  c.ch_max = 512
  c.impl = ''                    # '' = per backend: matmul on CPU, xla on GPU
  c.tau = 1.0                    # Gumbel-sigmoid temperature
  c.drop_const = -1.0            # drops as the discriminator sees them (<= -1)
  c.eqlr = 'authors'             # eq-lr constants: authors | fan_in (models.py)
  c.tolerance = 0.0              # baseline drop tolerance beta (evaluate --tune)

  # Optimisation (the paper's Implementation Details).
  c.batch_size = 32              # global, over all devices and hosts
  c.lr = 0.002
  c.beta1 = 0.0
  c.beta2 = 0.99
  c.adam_eps = 1e-8
  c.r1_gamma = 1.0
  c.r1_every = 1                 # R1 every step as the authors; k > 1: lazy (StyleGAN2)
  c.ema_halflife_kimg = 10.0
  c.ema_rampup = 0.0             # >0: half-life min(10k, rampup x images seen)
  c.augment = 'brightness,contrast,translation,cutout'
  c.augment_style = 'authors'    # authors | symmetric (augment.py)
  # The authors' schedule: 25,000 kimg = 781,250 steps at batch 32.
  c.num_steps = 25_000_000 // 32

  # Logging and checkpoints.
  c.log_every = 50
  c.image_every = 500
  c.checkpoint_every = 1000
  c.keep_checkpoints = 3
  c.num_images = 8               # samples in each PNG grid
  return c


class ConfigError(ValueError):
  """A config value that cannot work; the message names the field."""


# Fields that decide what a checkpoint holds: a run may not resume with
# other values (the saved arrays would not fit, or would mean something else).
ARCHITECTURE = ('model', 'latent_dim', 'ch_base', 'ch_max', 'eqlr', 'sensor')


def validate(c) -> None:
  """Checks a config before any work; raises ConfigError naming the field."""
  def need(ok, field, why):
    if not ok:
      raise ConfigError(f'config field {field}={c.get(field)!r}: {why}')
  need(c.model in ('baseline', 'dusty1', 'dusty2'), 'model',
       'known models are baseline, dusty1, dusty2')
  for f in ('batch_size', 'num_steps', 'log_every', 'image_every',
            'checkpoint_every', 'keep_checkpoints', 'latent_dim', 'ch_base',
            'ch_max', 'num_images'):
    need(isinstance(c[f], int) and c[f] >= 1, f, 'must be a whole number >= 1')
  need(c.lr > 0, 'lr', 'the learning rate must be > 0')
  need(0 <= c.beta1 < 1 and 0 <= c.beta2 < 1, 'beta1' if not 0 <= c.beta1 < 1
       else 'beta2', 'Adam betas must lie in [0, 1)')
  need(c.adam_eps > 0, 'adam_eps', 'must be > 0')
  need(c.r1_gamma >= 0, 'r1_gamma', 'must be >= 0')
  need(isinstance(c.r1_every, int) and c.r1_every >= 1, 'r1_every',
       'must be a whole number >= 1 (1: every step)')
  need(c.tau > 0, 'tau', 'the Gumbel temperature must be > 0')
  need(c.ema_halflife_kimg >= 0, 'ema_halflife_kimg', 'must be >= 0')
  need(c.get('drop_const', -1.0) <= -1.0, 'drop_const',
       'must be <= -1 (inside the depth range a drop would read as a surface)')


# Runs written before these options existed trained with what is now the
# non-default choice; their config.json lacks the field.
LEGACY = {'eqlr': 'fan_in', 'augment_style': 'symmetric', 'drop_const': -1.0}


def legacy_get(config, field: str):
  """A config field, or the value runs older than the field used."""
  return config.get(field, LEGACY[field])


def architecture_diff(old, new) -> dict:
  """{field: (old, new)} of the ARCHITECTURE fields that differ between two
  configs; fields a config predates take their LEGACY value."""
  out = {}
  for f in ARCHITECTURE:
    a, b = old.get(f, LEGACY.get(f)), new.get(f, LEGACY.get(f))
    if f == 'sensor':
      a, b = (a.to_dict() if hasattr(a, 'to_dict') else a,
              b.to_dict() if hasattr(b, 'to_dict') else b)
    if a != b:
      out[f] = (a, b)
  return out


# The study (benchmarks/study.py): baseline vs DUSty-I vs DUSty-II on the
# simulated HDL-64E scans. 'cpu' fits all three trainings in about 100
# minutes on 2 CPU cores; 'paper' is the paper's size and schedule.
STUDY_SCALES = ('cpu', 'paper')


def study(model: str, scale: str = 'cpu') -> ml_collections.ConfigDict:
  """``model``: baseline, dusty1, dusty2, or dusty1_noaug (DUSty-I without
  DiffAugment: at the CPU scale the discriminator cannot see point-drops
  through the augmentation, see benchmarks/results/study.md)."""
  if scale not in STUDY_SCALES:
    raise ValueError(f'unknown study scale {scale!r}; known: {list(STUDY_SCALES)}')
  c = default()
  c.model = model.split('_')[0]
  if model.endswith('_noaug'):
    c.augment = ''
  c.sensor.preset = 'kitti'
  c.data.dir = ''
  c.data.num_synthetic = 2000
  if scale == 'cpu':
    c.latent_dim = 128
    c.ch_base = 16
    c.ch_max = 128
    c.batch_size = 16
    c.ema_rampup = 0.05
    c.num_steps = 2500
    c.log_every = 50
    c.image_every = 500
    c.checkpoint_every = 250
  return c


def save(workdir: str, config):
  """Writes a run's config (atomically)."""
  os.makedirs(workdir, exist_ok=True)
  path = os.path.join(workdir, FILE)
  with open(path + '.tmp', 'w') as f:
    f.write(config.to_json(indent=2))
  os.replace(path + '.tmp', path)


def load(workdir: str) -> ml_collections.ConfigDict:
  """A run's config, as saved by :func:`save`."""
  path = os.path.join(workdir, FILE)
  if not os.path.isfile(path):
    raise FileNotFoundError(f'{path}: not a training run directory (no {FILE}); '
                            'train one with `python -m dusty_jax.train --workdir DIR`')
  with open(path) as f:
    try:
      return ml_collections.ConfigDict(json.load(f))
    except json.JSONDecodeError as e:
      raise ValueError(f'{path}: not valid JSON ({e})') from None
