"""Shared defaults for every experiment; experiments/*.py override a few.

The defaults train as the authors' code (kazuto1011/dusty-gan) does; every
deviation we prefer is an option here (README: "Differences from the
authors' code").
"""

from __future__ import annotations

import json
import os

import ml_collections

from dusty_jax import errors, models, sensor as sensor_lib

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

  # Beyond the paper: ways to make point-drops survive training at a small
  # scale (README "Point-drops that survive training"). All off by default.
  c.drops = drop_defaults()

  # Logging and checkpoints.
  c.log_every = 50
  c.image_every = 500
  c.checkpoint_every = 1000
  c.keep_checkpoints = 3
  c.keep_every = 0               # also keep each checkpoint whose step is a
                                 # multiple of this (0: none), for curves over training
  c.num_images = 8               # samples in each PNG grid
  return c


def drop_defaults() -> ml_collections.ConfigDict:
  """The point-drop mechanisms (trainer.DropOptions), all off."""
  d = ml_collections.ConfigDict()
  d.mask_channel = 0.0    # > 0: D also sees the keep-mask, x this weight
  d.mask_noise = 0.0      # std of Gaussian noise added to that channel
  d.mask_dropout = 0.0    # probability of hiding that channel, per example
  d.keep_drops = False    # DiffAugment keeps drops as drops (augment.with_mask)
  d.mask_bias = 0.0       # initial measurability logit (logit of the keep rate)
  d.mask_lr = 1.0         # update multiplier of the measurability head
  d.rate_weight = 0.0     # G: + weight x (generated keep rate - real keep rate)^2
  d.rate_by = 'image'     # image: one rate per batch | ring: one per row |
                          # ring_depth: per row and neighbours' depth bin
  d.rate_shrink = 0.0     # ring_depth: cell targets shrunk to the ring's rate,
                          # as if k more pixels kept at it
  d.rate_head_only = False  # the rate term trains the measurability head only,
                            # on its expected keep rate
  d.mask_detached = False   # no gradient of the mask reaches G's trunk: the
                            # measurability head works on its features, detached
  d.depth_weight = 0.0    # G: + weight x mean over rings of (mean returned
                          # inverse depth - real's)^2: anchors the range
  d.dip_weight = 0.0      # G: + weight x mean depth of the dips among its
                          # returns (pixels behind both ring neighbours)
  d.peak_weight = 0.0     # G: + weight x excess over the real scans' of the
                          # mean height of its peaks (in front of both)
  d.far_weight = 0.0      # G: + weight x mean over rings of (share of its
                          # pixels that are returns beyond FAR_M - real's)^2
  d.rate_skip_far = False # ring_depth: the cells beyond 40 m weigh 0 (far_weight
                          # alone sets the far keep rate)
  d.range_slope = False   # G: a learned slope per ring of the measurability
                          # logit in the pixel's own x_tilde, started at 0
  d.ring_bias = False     # G: a learned measurability offset per ring, started
                          # at the training data's keep rate of that ring
  return d


class ConfigError(errors.UserError, ValueError):
  """A config value that cannot work; the message names the field."""


# Fields that decide what a checkpoint holds: a run may not resume with
# other values (the saved arrays would not fit, or would mean something else).
ARCHITECTURE = ('model', 'latent_dim', 'ch_base', 'ch_max', 'eqlr', 'sensor', 'drops')


def _missing(c, want, prefix='') -> str | None:
  """The first field of ``want`` (a default config) that ``c`` lacks."""
  for k, v in want.items():
    if k not in c:
      return prefix + k
    if isinstance(v, ml_collections.ConfigDict) and isinstance(c[k], ml_collections.ConfigDict):
      missing = _missing(c[k], v, f'{prefix}{k}.')
      if missing:
        return missing
  return None


def validate(c) -> None:
  """Checks a config before any work; raises ConfigError naming the field.
  The one check: what is built from a valid config reads its fields as
  they are (every field of :func:`default` is present)."""
  missing = _missing(c, default())
  if missing:
    raise ConfigError(f'config field {missing} is missing: build experiment configs on '
                      'dusty_jax.configs.default() and override what differs')
  def need(ok, field, why):
    if not ok:
      raise ConfigError(f'config field {field}={c.get(field)!r}: {why}')
  need(c.model in models.VARIANTS, 'model',
       f'known models are {", ".join(models.VARIANTS)}')
  for f in ('batch_size', 'num_steps', 'log_every', 'image_every',
            'checkpoint_every', 'keep_checkpoints', 'latent_dim', 'ch_base',
            'ch_max', 'num_images'):
    need(isinstance(c[f], int) and c[f] >= 1, f, 'must be a whole number >= 1')
  need(isinstance(c.keep_every, int) and c.keep_every >= 0, 'keep_every',
       'must be a whole number >= 0 (0: keep the last keep_checkpoints only)')
  need(c.lr > 0, 'lr', 'the learning rate must be > 0')
  need(0 <= c.beta1 < 1 and 0 <= c.beta2 < 1, 'beta1' if not 0 <= c.beta1 < 1
       else 'beta2', 'Adam betas must lie in [0, 1)')
  need(c.adam_eps > 0, 'adam_eps', 'must be > 0')
  need(c.r1_gamma >= 0, 'r1_gamma', 'must be >= 0')
  need(isinstance(c.r1_every, int) and c.r1_every >= 1, 'r1_every',
       'must be a whole number >= 1 (1: every step)')
  need(c.tau > 0, 'tau', 'the Gumbel temperature must be > 0')
  need(c.ema_halflife_kimg >= 0, 'ema_halflife_kimg', 'must be >= 0')
  need(c.drop_const <= -1.0, 'drop_const',
       'must be <= -1 (inside the depth range a drop would read as a surface)')
  preset = c.sensor.preset
  if preset and preset not in sensor_lib.PRESETS:
    raise ConfigError(f'config field sensor.preset={preset!r}: known presets are '
                      f"{', '.join(sorted(sensor_lib.PRESETS))} ('' with "
                      'sensor.height and sensor.width: a tiny test sensor)')
  if not preset and not (c.sensor.height >= 1 and c.sensor.width >= 1):
    raise ConfigError('config field sensor.preset is empty: give a preset, or '
                      'sensor.height and sensor.width >= 1 for a tiny sensor')
  d = c.drops
  def need_drop(ok, field, why):
    if not ok:
      raise ConfigError(f'config field drops.{field}={d.get(field)!r}: {why}')
  for f in ('mask_channel', 'mask_noise', 'mask_dropout', 'rate_weight', 'rate_shrink',
            'depth_weight', 'dip_weight', 'peak_weight', 'far_weight'):
    need_drop(d[f] >= 0, f, 'must be >= 0')
  need_drop(d.mask_dropout <= 1, 'mask_dropout', 'a probability: must be <= 1')
  need_drop(d.mask_lr > 0, 'mask_lr', 'must be > 0')
  need_drop(d.rate_by in ('image', 'ring', 'ring_depth'), 'rate_by',
            "must be 'image', 'ring' or 'ring_depth'")
  need_drop(d.rate_shrink == 0 or d.rate_by == 'ring_depth', 'rate_shrink',
            f"acts only with rate_by='ring_depth' (rate_by is {d.rate_by!r})")
  need_drop(not d.rate_skip_far or d.rate_by == 'ring_depth', 'rate_skip_far',
            f"acts only with rate_by='ring_depth' (rate_by is {d.rate_by!r})")
  need_drop(not d.rate_head_only or d.rate_weight > 0, 'rate_head_only',
            'acts only on a rate term: set drops.rate_weight > 0')
  model_has_mask = models.get_variant(c.model).has_measurability
  acting = [f for f, off in (('mask_channel', 0), ('rate_weight', 0), ('far_weight', 0),
                             ('mask_bias', 0),
                             ('mask_lr', 1.0), ('ring_bias', False), ('range_slope', False),
                             ('mask_detached', False)) if d[f] != off]
  if acting:  # the first option set names the error
    need_drop(model_has_mask, acting[0], f'the {c.model} model has no measurability to act on')


# Runs written before these options existed trained with what is now the
# non-default choice (keep_every: kept as the default does); their
# config.json lacks the field.
LEGACY = {'eqlr': 'fan_in', 'augment_style': 'symmetric', 'drop_const': -1.0,
          'keep_every': 0}


def upgrade(config) -> ml_collections.ConfigDict:
  """The one translation of older configs: a copy in which each field the
  config predates holds the value such runs used (LEGACY), and the ``drops``
  group (runs from before it: all off) has every option."""
  c = ml_collections.ConfigDict(config.to_dict() if hasattr(config, 'to_dict') else config)
  for field, value in LEGACY.items():
    if field not in c:
      c[field] = value
  drops = drop_defaults()
  drops.update(c.drops.to_dict() if 'drops' in c else {})
  c.drops = drops
  return c


def model_settings(config) -> models.ModelSettings:
  """What a (possibly old) config says about the networks."""
  c = upgrade(config)
  return models.ModelSettings(model=c.model, latent_dim=int(c.latent_dim),
                              ch_base=int(c.ch_base), ch_max=int(c.ch_max),
                              eqlr=c.eqlr, tau=float(c.tau),
                              ring_bias=bool(c.drops.ring_bias),
                              range_slope=bool(c.drops.range_slope))


def architecture_diff(old, new) -> dict:
  """{field: (old, new)} of the ARCHITECTURE fields that differ between two
  configs; fields a config predates take their LEGACY value."""
  old, new = upgrade(old), upgrade(new)
  out = {}
  for f in ARCHITECTURE:
    a, b = old.get(f), new.get(f)
    if f == 'drops':  # only these change what the networks' arrays are.
      a, b = ((o.drops.mask_channel > 0, bool(o.drops.ring_bias),
               bool(o.drops.range_slope)) for o in (old, new))
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


# The point-drop variant the study ships (beyond the paper; README "Point-drops
# that survive training"): D sees the keep-mask as a noised channel hidden
# half the time, G matches the real keep rate, and the measurability starts
# at the data's keep rate (logit(0.8)).
DROPS_VARIANT = dict(mask_channel=1.0, mask_noise=0.1, mask_dropout=0.5,
                     rate_weight=10.0, mask_bias=1.386)
# Drops by ring and range (README "Point-drops that survive training"): G
# matches the real keep rate of each (ring, neighbours' depth) cell, and its
# measurability has one learned offset per ring, started at that ring's rate.
RANGE_DROPS_VARIANT = dict(rate_weight=100.0, rate_by='ring_depth', mask_bias=1.386,
                           ring_bias=True)
# The same, with the rate term training only the measurability head (on its
# expected keep rate): G's shared trunk is left to the GAN loss.
HEAD_DROPS_VARIANT = dict(RANGE_DROPS_VARIANT, rate_head_only=True)
# The same, with no gradient of the mask reaching the trunk at all (the GAN's
# straight-through one included): the trunk learns from x_tilde alone.
DETACHED_DROPS_VARIANT = dict(HEAD_DROPS_VARIANT, mask_detached=True)
# The same, with G also filling the dips among its returns (dip_weight): the
# far speckle that cost the mask-detached variant its depth at other seeds
# (README "Depth that survives the drops").
DIP_DROPS_VARIANT = dict(DETACHED_DROPS_VARIANT, dip_weight=10.0)
# The same, with G also paying for peaks among its returns beyond the real
# scans' (peak_weight): the lattice of near pixels the dips variant leaves.
PEAK_DROPS_VARIANT = dict(DIP_DROPS_VARIANT, peak_weight=10.0)
# The same, with G also holding each ring's share of far returns (beyond
# trainer.FAR_M, 40 m) to the real batch's (far_weight), through its drops:
# the far structure the peaks variant returns too often (benchmarks/far_returns.py).
# Its ring_depth rate term leaves out the cells beyond 40 m (rate_skip_far),
# which the far term owns: chosen over five seeds on the validation split
# (README "The rate term's far cells").
FAR_DROPS_VARIANT = dict(PEAK_DROPS_VARIANT, far_weight=100.0, rate_skip_far=True)
# Study model suffix -> the drops options it adds (beyond the paper).
STUDY_DROPS = {'_drops': DROPS_VARIANT, '_rangedrops': RANGE_DROPS_VARIANT,
               '_headdrops': HEAD_DROPS_VARIANT, '_detdrops': DETACHED_DROPS_VARIANT,
               '_dipdrops': DIP_DROPS_VARIANT, '_peakdrops': PEAK_DROPS_VARIANT,
               '_fardrops': FAR_DROPS_VARIANT}


def study(model: str, scale: str = 'cpu') -> ml_collections.ConfigDict:
  """``model``: baseline, dusty1, dusty2, dusty1_noaug (DUSty-I without
  DiffAugment: at the CPU scale the discriminator cannot see point-drops
  through the augmentation, see benchmarks/results/study.md), or
  dusty1_drops / dusty2_drops (with DROPS_VARIANT), dusty1_rangedrops /
  dusty2_rangedrops (with RANGE_DROPS_VARIANT), dusty1_headdrops /
  dusty2_headdrops (with HEAD_DROPS_VARIANT), dusty1_detdrops /
  dusty2_detdrops (with DETACHED_DROPS_VARIANT), dusty1_dipdrops /
  dusty2_dipdrops (with DIP_DROPS_VARIANT), dusty1_peakdrops /
  dusty2_peakdrops (with PEAK_DROPS_VARIANT), or dusty1_fardrops /
  dusty2_fardrops (with FAR_DROPS_VARIANT)."""
  if scale not in STUDY_SCALES:
    raise ValueError(f'unknown study scale {scale!r}; known: {list(STUDY_SCALES)}')
  c = default()
  c.model = model.split('_')[0]
  if model.endswith('_noaug'):
    c.augment = ''
  for suffix, options in STUDY_DROPS.items():
    if model.endswith(suffix):
      c.drops.update(options)
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
  """A run's config, as saved by :func:`save`, older formats translated
  (:func:`upgrade`)."""
  path = os.path.join(workdir, FILE)
  if not os.path.isfile(path):
    raise FileNotFoundError(f'{path}: not a training run directory (no {FILE}); '
                            'train one with `python -m dusty_jax.train --workdir DIR`')
  with open(path) as f:
    try:
      return upgrade(json.load(f))
    except json.JSONDecodeError as e:
      raise ValueError(f'{path}: not valid JSON ({e})') from None
