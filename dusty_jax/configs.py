"""Shared defaults for every experiment; experiments/*.py override a few.

The defaults train as the authors' code (kazuto1011/dusty-gan) does; every
deviation we prefer is an option here.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import os

import ml_collections

from dusty_jax import drops as drops_lib, errors, files, gumbel, models, sensor as sensor_lib
from dusty_jax.data import arrays

FILE = 'config.json'  # a run's config, in its directory


def default() -> ml_collections.ConfigDict:
  c = ml_collections.ConfigDict()
  c.seed = 0
  c.model = 'dusty1'             # baseline | dusty1 | dusty2

  c.sensor = ml_collections.ConfigDict()
  c.sensor.preset = 'kitti'      # a name of sensor.PRESETS: kitti (HDL-64E 64x256),
                                 # mpo (HDL-32E 32x256), vlp16, hdl32e, hdl64e, os1-64, os1-128
  c.sensor.file = ''             # a sensor spec JSON file (sensor.load); wins over preset
  c.sensor.height = 0            # with preset '', a tiny sensor of this size
  c.sensor.width = 0             # 0: the preset's width

  c.data = ml_collections.ConfigDict()
  c.data.name = ''               # kitti | mpo, for messages
  c.data.dir = ''                # prepared arrays; '' = simulated scenes
  c.data.num_synthetic = 2000    # simulated training scans (default data)
  c.data.seed = 0
  c.data.cache = ''              # '' = ~/.cache/dusty_jax
  c.data.memory_mb = arrays.MEMORY_MB  # a training split up to this is read into memory
  c.data.allow_changed = False   # resume on data other than the run trained on

  # Networks (the paper's Table I).
  c.latent_dim = 512
  c.ch_base = 64
  c.ch_max = 512
  c.impl = ''                    # '' = per backend: matmul on CPU, xla on GPU
  c.tau = 1.0                    # Gumbel-sigmoid temperature
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

  # Beyond the paper: point-drop mechanisms (drops.DropOptions describes
  # each). All off by default.
  c.drops = drop_defaults()

  # Logging and checkpoints.
  c.log_every = 50
  c.image_every = 500
  c.checkpoint_every = 1000
  c.checkpoint_minutes = 10.0    # also save when this many minutes passed since the
                                 # last save (0: by steps only)
  c.keep_checkpoints = 3
  c.keep_every = 0               # also keep each checkpoint whose step is a
                                 # multiple of this (0: none), for curves over training
  c.num_images = 8               # samples in each PNG grid

  # A short evaluation when training ends (evaluation.after_training):
  # final_evaluation.json and .png in the run directory. 0 scans: skipped.
  c.final_eval = ml_collections.ConfigDict()
  c.final_eval.num_synthesis = 0  # test scans of Table II (one seed)
  c.final_eval.points = 512       # points per cloud there
  c.final_eval.num_invert = 0     # test scans inverted (drop placement with ground truth)
  c.final_eval.invert_steps = 300

  # What runs after the last step, in order (comma-separated names of
  # AFTER_TRAINING); each acts where its own fields ask for it.
  c.after_training = ','.join(AFTER_TRAINING)
  return c


def drop_defaults() -> ml_collections.ConfigDict:
  """The point-drop options, all off: drops.DropOptions' (which describes
  each), and ring_bias, which changes the networks: a learned logit offset
  per ring on G's pixel measurability (models.ModelSettings.ring_bias),
  started at the training data's keep rate of that ring
  (drops.set_ring_bias)."""
  return ml_collections.ConfigDict(dict(dataclasses.asdict(drops_lib.DropOptions()),
                                        ring_bias=False))


class ConfigError(errors.UserError, ValueError):
  """A config value that cannot work; the message names the field."""


# Fields that decide what a checkpoint holds: a run may not resume with
# other values (the saved arrays would not fit, or would mean something else).
# The sensor too, compared as the spec the run recorded (runs.check_resumable).
ARCHITECTURE = ('model', 'latent_dim', 'ch_base', 'ch_max', 'eqlr', 'drops')


def _missing(c, want, prefix='') -> str | None:
  """The first field of ``want`` (a default config) that ``c`` lacks."""
  for k, v in want.items():
    if k not in c:
      return prefix + k
    if isinstance(v, ml_collections.ConfigDict) and hasattr(c[k], 'keys'):
      missing = _missing(c[k], v, f'{prefix}{k}.')
      if missing:
        return missing
  return None


# The steps after training (after_training.STEPS, which the trainer runs):
#   levels: fits the EMA generator's drop levels, where drops.depth_levels;
#   final_evaluation: the short evaluation of final_eval, where it has scans.
AFTER_TRAINING = ('levels', 'final_evaluation')


def after_training(c) -> tuple:
  """The names of the steps ``c.after_training`` lists, in order."""
  return tuple(n.strip() for n in c.after_training.split(',') if n.strip())


IMPLS = ('', 'matmul', 'xla')  # config field impl (layers.py)
# The drops options that act on a measurability, with the value that is off.
DROPS_OFF = (('rate_weight', 0), ('mask_bias', 0), ('ring_bias', False),
             ('mask_detached', False), ('depth_levels', False))


def _finite(v) -> bool:
  """A real number (not a bool), neither NaN nor inf."""
  return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


def validate(c) -> sensor_lib.SensorSpec:
  """Checks a config before any work; raises ConfigError naming the field
  (the augmentation fields: augment.check_config, beside the names it
  checks, since loading a generator reads configs and needs no augment.py).
  The one check: what is built from a valid config reads its fields as
  they are (every field of :func:`default` is present). Returns the sensor
  the config names, resolved (sensor.from_config): the trainer's start
  calls this once, and everything below it takes that SensorSpec."""
  missing = _missing(c, default())
  if missing:
    raise ConfigError(f'config field {missing} is missing: build experiment configs on '
                      'dusty_jax.configs.default() and override what differs')
  _need(c, c.model in models.VARIANTS, 'model',
        f'known models are {", ".join(models.VARIANTS)}')
  _check_counts(c)
  _check_optimiser(c)
  sensor = _sensor(c)
  _check_drops(c)
  return sensor


def _need(c, ok, field, why):
  if not ok:
    raise ConfigError(f'config field {field}={c.get(field)!r}: {why}')


def _check_counts(c):
  """The whole-number fields: steps, sizes, logging, checkpoints, final_eval."""
  for f in ('batch_size', 'num_steps', 'log_every', 'image_every',
            'checkpoint_every', 'keep_checkpoints', 'latent_dim', 'ch_base',
            'ch_max', 'num_images'):
    _need(c, isinstance(c[f], int) and 1 <= c[f] <= errors.INT32_MAX, f,
          'must be a whole number >= 1 (and <= 2**31 - 1, an int32 once compiled)')
  _need(c, isinstance(c.keep_every, int) and c.keep_every >= 0, 'keep_every',
        'must be a whole number >= 0 (0: keep the last keep_checkpoints only)')
  minutes = c.checkpoint_minutes
  _need(c, isinstance(minutes, (int, float)) and not isinstance(minutes, bool)
        and 0 <= minutes < float('inf'), 'checkpoint_minutes',
        'must be a number of minutes >= 0 (0: save by steps only)')
  for f in ('num_synthesis', 'points', 'num_invert', 'invert_steps'):
    v = c.final_eval[f]
    if not (isinstance(v, int) and v >= (1 if f in ('points', 'invert_steps') else 0)):
      raise ConfigError(f'config field final_eval.{f}={v!r}: must be a whole number >= '
                        f'{1 if f in ("points", "invert_steps") else "0 (0: skipped)"}')
  if not (isinstance(c.data.memory_mb, int) and c.data.memory_mb >= 0):
    raise ConfigError(f'config field data.memory_mb={c.data.memory_mb!r}: must be a whole '
                      'number of MiB >= 0 (0: always read the training split from its file)')
  unknown = [n for n in after_training(c) if n not in AFTER_TRAINING]
  _need(c, not unknown, 'after_training', unknown and f'{unknown[0]!r} is no step after '
        f"training; give a comma-separated list of {', '.join(AFTER_TRAINING)} ('' for none)")


def _check_optimiser(c):
  """The optimisation's numbers (Adam, R1, tau, EMA) and the networks' options."""
  _need(c, _finite(c.lr) and c.lr > 0, 'lr', 'the learning rate must be a finite number > 0')
  _need(c, 0 <= c.beta1 < 1 and 0 <= c.beta2 < 1, 'beta1' if not 0 <= c.beta1 < 1
        else 'beta2', 'Adam betas must lie in [0, 1)')
  _need(c, _finite(c.adam_eps) and c.adam_eps > 0, 'adam_eps', 'must be a finite number > 0')
  _need(c, _finite(c.r1_gamma) and c.r1_gamma >= 0, 'r1_gamma',
        'must be a finite number >= 0')
  _need(c, isinstance(c.r1_every, int) and c.r1_every >= 1, 'r1_every',
        'must be a whole number >= 1 (1: every step)')
  lo, hi = gumbel.TAU_RANGE
  _need(c, _finite(c.tau) and lo <= c.tau <= hi, 'tau', f'the Gumbel temperature must lie '
        f'in [{lo:g}, {hi:g}]: beyond, its straight-through gradient vanishes or stops '
        'depending on the logits (gumbel.TAU_RANGE)')
  # Beyond this half-life a step's weight in the EMA, 1 - 0.5 ** (batch /
  # half-life), is below float32's resolution near 1 (2**-24): it never moves.
  frozen = c.batch_size * math.log(2) * 2 ** 24 / 1000
  _need(c, _finite(c.ema_halflife_kimg) and 0 <= c.ema_halflife_kimg <= frozen,
        'ema_halflife_kimg', f'must lie in [0, {frozen:.4g}] for batch_size '
        f'{c.batch_size} (0: the EMA is the generator; longer: float32 leaves it at init)')
  _need(c, _finite(c.ema_rampup) and c.ema_rampup >= 0, 'ema_rampup',
        'must be a finite number >= 0 (0: no ramp-up)')
  _need(c, c.impl in IMPLS, 'impl', "must be '' (per backend: matmul on CPU, xla "
        "elsewhere), 'matmul' or 'xla'")
  _need(c, c.eqlr in models.EQLR, 'eqlr', f"must be one of {', '.join(map(repr, models.EQLR))}")


def _sensor(c) -> sensor_lib.SensorSpec:
  """The config's sensor, resolved and checked against the networks' shapes."""
  preset, file = c.sensor.preset, c.sensor.get('file')
  if preset and not file and preset not in sensor_lib.PRESETS:
    raise ConfigError(f'config field sensor.preset={preset!r}: known presets are '
                      f"{', '.join(sorted(sensor_lib.PRESETS))} ('' with "
                      'sensor.height and sensor.width: a tiny test sensor; or '
                      'sensor.file=PATH: a sensor spec file)')
  if not preset and not file and not (c.sensor.height >= 1 and c.sensor.width >= 1):
    raise ConfigError('config field sensor.preset is empty: give a preset, '
                      'sensor.file, or sensor.height and sensor.width >= 1 for a '
                      'tiny sensor')
  try:
    spec = sensor_lib.from_config(c.sensor)
    models.check_shape(spec)
  except ValueError as e:  # DataError too: the file, named in its message
    field = 'sensor.file' if file else 'sensor.width' if c.sensor.width else 'sensor.preset'
    raise ConfigError(f'config field {field}={c.sensor[field.split(".")[1]]!r}: {e}') from None
  return spec


def _check_drops(c):
  """The point-drop options: weights >= 0, and none acting on a model with no
  measurability."""
  d = c.drops
  def need_drop(ok, field, why):
    if not ok:
      raise ConfigError(f'config field drops.{field}={d.get(field)!r}: {why}')
  for f in ('rate_weight', 'dip_weight'):
    need_drop(d[f] >= 0, f, 'must be >= 0')
  need_drop(not d.rate_head_only or d.rate_weight > 0, 'rate_head_only',
            'acts only on a rate term: set drops.rate_weight > 0')
  model_has_mask = models.get_variant(c.model).has_measurability
  acting = [f for f, off in DROPS_OFF if d[f] != off]
  if acting:  # the first option set names the error
    off = dict(DROPS_OFF)[acting[0]]
    need_drop(model_has_mask, acting[0], f'the {c.model} model has no measurability to act '
              f'on: set drops.{acting[0]}={off!r}, or train it with --config '
              f'experiments/study.py:{c.model}')


def model_settings(c) -> models.ModelSettings:
  """What a config says about the networks."""
  return models.ModelSettings(model=c.model, latent_dim=int(c.latent_dim),
                              ch_base=int(c.ch_base), ch_max=int(c.ch_max),
                              eqlr=c.eqlr, tau=float(c.tau),
                              ring_bias=bool(c.drops.ring_bias))


def architecture_diff(old, new) -> dict:
  """{field: (old, new)} of the ARCHITECTURE fields that differ between two
  configs."""
  out = {}
  for f in ARCHITECTURE:
    a, b = old.get(f), new.get(f)
    if f == 'drops':  # only these change what the networks' arrays are.
      a, b = (bool(o.drops.ring_bias) for o in (old, new))
    if a != b:
      out[f] = (a, b)
  return out


def save(workdir: str, config):
  """Writes a run's config (atomically)."""
  os.makedirs(workdir, exist_ok=True)
  path = os.path.join(workdir, FILE)
  with files.atomic_write(path) as f:
    f.write(config.to_json(indent=2))


# What a run adds to its config: the devices it trained on
# (runs.as_trained); a converted .pth's source and step (authors.load).
RUN_FIELDS = ('trained_on', 'source_checkpoint', 'source_step')
# A field added to default() takes, in a run from before it, its default,
# which does what such runs did (the rule for adding one). A run config
# holding a field since removed, or lacking one whose default changed when
# it came (eqlr, augment_style: runs without them used the other value), is
# a research-era run: not translated.
CHANGED_DEFAULTS = ('eqlr', 'augment_style')
RESEARCH_ERA = ('written by a research-era dusty_jax; dusty_jax 0.1.0 is the last version '
                'that reads it')


def _unknown(c, want, prefix='') -> str | None:
  """The first field of ``c`` that ``want`` (a default config) lacks."""
  for k, v in c.items():
    if k not in want:
      return prefix + k
    if isinstance(v, dict) and isinstance(want[k], ml_collections.ConfigDict):
      unknown = _unknown(v, want[k], f'{prefix}{k}.')
      if unknown:
        return unknown
  return None


def _fill(c: dict, want: dict) -> dict:
  """``c`` with the fields of ``want`` it lacks, groups field by field."""
  out = dict(c)
  for k, v in want.items():
    if k not in out:
      out[k] = v
    elif isinstance(v, dict) and isinstance(out[k], dict):
      out[k] = _fill(out[k], v)
  return out


def load(workdir: str) -> ml_collections.ConfigDict:
  """A run's config, as saved by :func:`save` (fields added since take their
  defaults); ConfigError for one of a research-era version."""
  path = os.path.join(workdir, FILE)
  if not os.path.isfile(path):
    raise FileNotFoundError(f'{path}: not a training run directory (no {FILE}); '
                            'train one with `python -m dusty_jax.train --workdir DIR`')
  with open(path) as f:
    try:
      saved = json.load(f)
    except json.JSONDecodeError as e:
      raise ValueError(f'{path}: not valid JSON ({e})') from None
  # Every config this library has saved names its model and sensor.
  missing = [k for k in ('model', 'sensor') if not isinstance(saved, dict) or k not in saved]
  if missing:
    raise ValueError(f'{path}: not a dusty_jax run config (no {missing[0]!r} field), so '
                     f'{workdir} is no training run of this library')
  # Runs of 2026-11-27 and -28 also kept their sensor's spec in the config
  # (sensor.spec); generator.json, written beside it, holds it (runs.py).
  if isinstance(saved.get('sensor'), dict):
    saved['sensor'].pop('spec', None)
  want = default()
  unknown = _unknown({k: v for k, v in saved.items() if k not in RUN_FIELDS}, want)
  gap = next((f for f in CHANGED_DEFAULTS if f not in saved), None)
  if unknown or gap:
    raise ConfigError(f'{path}: ' + (f'field {unknown} is no field of this version'
                                     if unknown else f'field {gap} is missing') +
                      f'; {RESEARCH_ERA}')
  return ml_collections.ConfigDict(_fill(saved, want.to_dict()))
