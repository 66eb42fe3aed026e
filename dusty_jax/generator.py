"""What a trained generator is, in memory and on disk.

In memory, :class:`GeneratorParams`: the generator's Flax variables and the
angle table (pytree leaves), with the sensor, the model settings and the drop
tolerance as static metadata. It is what ``sample``, ``generate`` and
``invert`` take, and it passes through jit, vmap and grad.

On disk, two forms, both read without the trainer, the discriminator, the
optimiser states or the data pipeline:
  * a training run directory: ``generator.json`` (sensor, model settings,
    tolerance) and ``angles.npy``, written when training starts, the drop
    levels fitted after it where it fitted them (levels.FILE), plus the
    generator's variables inside the run's orbax checkpoints (only they are
    read); runs older than ``generator.json`` are described by their
    ``config.json``;
  * one ``.npz`` file (:func:`export` / :func:`load_file`): what
    dusty_jax/pretrained ships.
:func:`load` (public as ``dusty_jax.load_checkpoint``) also takes the authors'
``.pth`` checkpoints (authors.py).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import zipfile
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct, traverse_util

from dusty_jax import checkpoint, configs, encoder as encoder_lib, files, levels
from dusty_jax.data import arrays
from dusty_jax.models import ModelSettings
from dusty_jax.sensor import SensorSpec, check_angles, from_config as sensor_from_config

SPEC_FILE = 'generator.json'
ENCODER_FILE = 'encoder.npz'  # a run's encoder (encoder.py), beside SPEC_FILE
FORMAT = 2  # 2: an exported .npz may hold an encoder (encoder.py); 1 reads as before


class GeneratorParams(struct.PyTreeNode):
  """A trained generator as one pytree: what sample() and invert() take."""
  variables: Any
  angles: Any  # (2, H, W) per-pixel elevation, azimuth for back-projection.
  sensor: SensorSpec = struct.field(pytree_node=False, default=None)
  settings: ModelSettings = struct.field(pytree_node=False, default=ModelSettings())
  tolerance: float = struct.field(pytree_node=False, default=0.0)
  # The encoder that starts inversion (encoder.py), or None: its variables
  # and its network's size.
  encoder: Any = None
  encoder_settings: encoder_lib.EncoderSettings | None = struct.field(
      pytree_node=False, default=None)

  # The settings most callers read, by name.
  model = property(lambda self: self.settings.model)
  latent_dim = property(lambda self: self.settings.latent_dim)
  tau = property(lambda self: self.settings.tau)
  variant = property(lambda self: self.settings.variant)

  def module(self, impl: str | None = None):
    """The generator network (Flax module) these variables belong to."""
    return self.settings.generator(self.sensor, impl)


# ----------------------------------------------------------------------------
# The description saved beside the variables: sensor, settings, tolerance.
# ----------------------------------------------------------------------------


def describe(sensor: SensorSpec, settings: ModelSettings, tolerance: float = 0.0) -> dict:
  return {'format': FORMAT, 'sensor': sensor.to_dict(),
          'settings': dataclasses.asdict(settings), 'tolerance': float(tolerance)}


def _from_description(d: dict, source: str):
  if d.get('format', FORMAT) > FORMAT:
    raise ValueError(f"{source}: written in generator format {d['format']} by a newer "
                     f'dusty_jax (this one reads up to {FORMAT}); upgrade dusty_jax')
  settings = d.get('settings')
  if not isinstance(settings, dict):  # files from before format 1: flat fields
    raise configs.ConfigError(f'{source}: no model settings; {configs.RESEARCH_ERA}')
  unknown = sorted(set(settings) - {f.name for f in dataclasses.fields(ModelSettings)})
  if unknown:
    raise configs.ConfigError(f'{source}: settings.{unknown[0]} is no model setting of '
                              f'this version; {configs.RESEARCH_ERA}')
  try:
    return (SensorSpec.from_dict(d['sensor']), ModelSettings(**settings),
            float(d.get('tolerance', 0.0)))
  except (KeyError, TypeError, ValueError) as e:
    raise ValueError(f'{source}: not a generator description ({e})') from None


def save_spec(workdir: str, sensor: SensorSpec, settings: ModelSettings, angles,
              tolerance: float = 0.0):
  """Writes ``generator.json`` and ``angles.npy`` into a run (atomically)."""
  angles = np.asarray(angles, np.float32)
  check_angles(angles, sensor.shape, f'sensor {sensor.name!r}: ')
  os.makedirs(workdir, exist_ok=True)
  arrays.save_array(os.path.join(workdir, arrays.ANGLES), angles)
  _write_spec(workdir, sensor, settings, tolerance)


def set_tolerance(workdir: str, tolerance: float):
  """Records a tuned drop tolerance (the baseline's beta) in a run (a run
  from before generator.json gets one, described by its config.json)."""
  sensor, settings, _ = read_spec(workdir)
  _write_spec(workdir, sensor, settings, tolerance)


def _write_spec(workdir, sensor, settings, tolerance):
  path = os.path.join(workdir, SPEC_FILE)
  with files.atomic_write(path) as f:
    json.dump(describe(sensor, settings, tolerance), f, indent=2)


def read_spec(workdir: str):
  """(sensor, settings, tolerance) of a run directory.

  Runs written before ``generator.json`` existed are described by their
  ``config.json`` (fields they predate take their legacy values).
  """
  path = os.path.join(workdir, SPEC_FILE)
  if os.path.isfile(path):
    with open(path) as f:
      try:
        d = json.load(f)
      except json.JSONDecodeError as e:
        raise ValueError(f'{path}: not valid JSON ({e})') from None
    return _from_description(d, path)
  config = configs.load(workdir)
  return (sensor_from_config(config.sensor), configs.model_settings(config),
          float(config.get('tolerance', 0.0)))


def read_angles(workdir: str, sensor: SensorSpec, angles=None) -> np.ndarray:
  """The run's angle table; ``angles``: a .npy path or 'nominal' instead."""
  if isinstance(angles, str) and angles == 'nominal':
    return sensor.nominal_angles()
  if angles is not None:
    from dusty_jax import authors  # the .pth / .pt reader, only when one is given
    return authors.read_angles(angles, sensor)
  if not os.path.isfile(os.path.join(workdir, arrays.ANGLES)):
    raise FileNotFoundError(
        f'{workdir}: no {arrays.ANGLES} (a run from before runs kept their angle '
        "table); copy its dataset's angles.npy into it, or pass angles= that file "
        "(angles='nominal': the sensor's nominal angles, which simulated data uses)")
  return arrays.load_angles(workdir, sensor)


# ----------------------------------------------------------------------------
# Loading.
# ----------------------------------------------------------------------------


MODEL_FORMS = ("a model is a run directory, a shipped model's name, an exported .npz "
               "or an authors' .pth")


def load(path: str, step: int | None = None, ema: bool = True,
         config: str | None = None, angles: str | None = None, log=None):
  """(GeneratorParams, config): the EMA generator by default.

  ``path`` is one of:
    * a run directory: the newest checkpoint that restores, or ``step``;
      ``config`` is the run's training config (None if only generator.json,
      angles.npy and checkpoints/ were copied);
    * a ``.npz`` written by :func:`export` (``config`` None; ``ema`` does
      not apply: the file holds one generator);
    * one of the authors' ``.pth`` checkpoints, with ``config=`` their yaml
      (default: found beside it).
  ``angles``: a (2, H, W) ``.npy`` table (or the authors' angles.pt, or
  'nominal') in place of the one the run or file holds (runs from before
  runs kept one need it). Nothing is written, simulated or read from a
  dataset. A run's ``depth_levels.npz`` (levels.py) is applied to the EMA
  generator of the step it fits. ``log`` (default: stderr) gets a warning
  per damaged checkpoint skipped, then the step loaded.
  """
  # The shipped models' folder (pretrained/ imports this module: read it as files).
  shipped = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'pretrained')
  if not os.path.exists(path) and os.path.isfile(os.path.join(shipped, f'{path}.npz')):
    raise FileNotFoundError(f"{path}: no such run directory or file; {path!r} is a "
                            'pretrained model: load it with '
                            f'dusty_jax.load_pretrained({path!r})')
  if os.path.isfile(path):
    if os.path.basename(path) in (configs.FILE, SPEC_FILE):
      what = 'config' if os.path.basename(path) == configs.FILE else 'generator description'
      raise ValueError(f"{path}: a training run's {what} file, not a checkpoint; pass "
                       f'its directory, {os.path.dirname(os.path.abspath(path))}')
    if step is not None:
      raise ValueError(f'{path}: step= is for a run directory, not a single file')
    if path.endswith('.npz'):
      params = load_file(path)
      if angles is not None:
        params = params.replace(angles=jnp.asarray(
            read_angles(path, params.sensor, angles), jnp.float32))
      return params, None
    if not zipfile.is_zipfile(path):  # what torch.save writes
      raise ValueError(f"{path}: not a model file (an authors' .pth is a torch.save zip "
                       f'file); {MODEL_FORMS}')
    from dusty_jax import authors  # the .pth reader, only when one is given
    fields, run_config = authors.load(path, config=config, ema=ema, angles=angles)
    return GeneratorParams(**fields), run_config
  if config is not None:
    raise ValueError(f"{path}: config= is for an authors' .pth; a run directory "
                     'holds its own')
  has_spec = os.path.isfile(os.path.join(path, SPEC_FILE))
  run_config = (configs.load(path) if not has_spec or
                os.path.isfile(os.path.join(path, configs.FILE)) else None)
  sensor, settings, tolerance = read_spec(path)
  table = read_angles(path, sensor, angles)
  name = 'ema_params' if ema else 'g_params'
  log = log or (lambda m: print(m, file=sys.stderr))
  variables, restored = checkpoint.restore_item(os.path.join(path, checkpoint.DIRECTORY),
                                                name, step, log=log)
  params = GeneratorParams(variables=variables, angles=jnp.asarray(table, jnp.float32),
                           sensor=sensor, settings=settings, tolerance=tolerance)
  check(params, path)
  fitted = levels.load(path) if ema else None  # the EMA's drop levels (levels.py)
  if fitted is not None:
    if fitted[1] == restored:
      params = levels.with_levels(params, fitted[0], os.path.join(path, levels.FILE))
    else:
      log(f'{os.path.join(path, levels.FILE)} fits step {fitted[1]}; step {restored} is '
          'loaded without those drop levels')
  enc_path = os.path.join(path, ENCODER_FILE)
  if os.path.isfile(enc_path):
    enc, enc_settings, _ = load_encoder(enc_path)
    params = params.replace(encoder=enc, encoder_settings=enc_settings)
    check_encoder(params, enc_path)
  return params, run_config


def check(params: GeneratorParams, source: str = 'generator'):
  """Refuses variables that do not fit the described network."""
  want = jax.eval_shape(params.module().init, jax.random.key(0),
                        jnp.zeros((1, params.latent_dim)))
  shape = lambda t: jax.tree.map(lambda v: tuple(np.shape(v)), t)
  if shape(want) != shape(params.variables):
    raise ValueError(f'{source}: the saved generator variables do not fit the '
                     f'described network ({params.settings}, sensor '
                     f'{params.sensor.shape})')


def export(params: GeneratorParams, path: str, source: str = '',
           training: dict | None = None) -> str:
  """Writes a generator as one ``.npz`` (variables, angles, description,
  and its encoder if it has one, under ``encoder/``). ``training``: how it
  was trained (config file, options beyond the paper, steps), kept in the
  file's ``meta`` for :func:`read_meta`."""
  meta = dict(describe(params.sensor, params.settings, params.tolerance), source=source)
  if training:
    meta['training'] = training
  arrs = {f'variables/{k}': v for k, v in flatten(params.variables).items()}
  if params.encoder is not None:
    meta['encoder'] = dataclasses.asdict(params.encoder_settings)
    arrs.update({f'encoder/{k}': v for k, v in flatten(params.encoder).items()})
  np.savez_compressed(path, meta=np.asarray(json.dumps(meta)),
                      angles=np.asarray(params.angles, np.float32), **arrs)
  return path


def read_meta(path: str) -> dict:
  """The description an exported ``.npz`` carries (sensor, settings,
  tolerance, source, training, encoder settings), without loading arrays."""
  with np.load(path, allow_pickle=False) as f:
    return json.loads(str(f['meta']))


def load_file(path: str) -> GeneratorParams:
  """A generator written by :func:`export`."""
  with np.load(path, allow_pickle=False) as f:
    if 'meta' not in f.files:
      raise ValueError(f'{path}: not a generator exported by dusty_jax (no meta in the '
                       f'archive); {MODEL_FORMS}')
    meta = json.loads(str(f['meta']))
    flat = {k[len('variables/'):]: f[k] for k in f.files if k.startswith('variables/')}
    enc = {k[len('encoder/'):]: f[k] for k in f.files if k.startswith('encoder/')}
    table = jnp.asarray(f['angles'])
  sensor, settings, tolerance = _from_description(meta, path)
  params = GeneratorParams(variables=unflatten(flat),
                           angles=table, sensor=sensor, settings=settings,
                           tolerance=tolerance)
  check(params, path)
  if enc:  # format 2
    params = params.replace(encoder=unflatten(enc),
                            encoder_settings=encoder_lib.EncoderSettings(**meta['encoder']))
    check_encoder(params, path)
  return params


# ----------------------------------------------------------------------------
# A run's encoder (encoder.py) on disk: ENCODER_FILE in the run directory;
# the same arrays inside an exported generator .npz, under encoder/.
# ----------------------------------------------------------------------------


def flatten(variables) -> dict:
  """{'a/b/c': float32 array} of a variables tree, as the .npz files hold it."""
  return {k: np.asarray(v, np.float32)
          for k, v in traverse_util.flatten_dict(variables, sep='/').items()}


def unflatten(flat: dict):
  return traverse_util.unflatten_dict({k: jnp.asarray(v) for k, v in flat.items()},
                                      sep='/')


def save_encoder(path: str, variables, settings: encoder_lib.EncoderSettings,
                 info: dict | None = None):
  """Writes an encoder's variables and settings as one .npz (atomically)."""
  meta = {**(info or {}), 'settings': dataclasses.asdict(settings)}
  with files.atomic_write(path, 'wb') as f:
    np.savez_compressed(f, meta=np.asarray(json.dumps(meta)),
                        **{f'encoder/{k}': v for k, v in flatten(variables).items()})
  return path


def load_encoder(path: str):
  """(variables, settings, meta) of an encoder written by :func:`save_encoder`."""
  try:
    with np.load(path, allow_pickle=False) as f:
      meta = json.loads(str(f['meta']))
      flat = {k[len('encoder/'):]: f[k] for k in f.files if k.startswith('encoder/')}
  except (OSError, ValueError, KeyError) as e:
    raise ValueError(f'{path}: not an encoder file ({e})') from None
  try:
    settings = encoder_lib.EncoderSettings(**meta['settings'])
  except (KeyError, TypeError) as e:
    raise ValueError(f'{path}: not an encoder description ({e})') from None
  return unflatten(flat), settings, meta


def check_encoder(params: GeneratorParams, source: str):
  """Refuses encoder variables that do not fit the described network."""
  want = jax.eval_shape(encoder_lib.module(params).init, jax.random.key(0),
                        jnp.zeros((1,) + params.sensor.shape))
  shape = lambda t: jax.tree.map(lambda v: tuple(np.shape(v)), t)
  if shape(want) != shape(params.encoder):
    raise ValueError(f'{source}: the encoder does not fit this generator (latent '
                     f'{params.latent_dim}, sensor {params.sensor.shape}, '
                     f'{params.encoder_settings}); retrain it with '
                     f'`{encoder_lib.TRAIN_COMMAND}`')
