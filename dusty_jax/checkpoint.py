"""The one place that knows about orbax: save, restore, and load for users."""

from __future__ import annotations

import json
import os
import time

import jax
import ml_collections
import orbax.checkpoint as ocp

CONFIG_FILE = 'config.json'
ANGLES_FILE = 'angles.npy'  # the same name as in a prepared dataset


def manager(workdir: str, keep: int = 3, interval: int = 1) -> ocp.CheckpointManager:
  path = os.path.join(os.path.abspath(workdir), 'checkpoints')
  opts = ocp.CheckpointManagerOptions(max_to_keep=keep,
                                      save_interval_steps=interval, create=True)
  return ocp.CheckpointManager(path, options=opts)


def save(mngr: ocp.CheckpointManager, step: int, state, force: bool = False) -> bool:
  return mngr.save(step, args=ocp.args.StandardSave(state), force=force)


def restore(mngr: ocp.CheckpointManager, step: int, target):
  """The state saved at ``step``, shaped like ``target``."""
  abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, target)
  return mngr.restore(step, args=ocp.args.StandardRestore(abstract))


def restore_latest(mngr: ocp.CheckpointManager, target, log=print,
                   set_aside: bool = False):
  """(state, step) from the newest checkpoint that restores, or (target, None).

  A damaged checkpoint (truncated file, missing metadata, empty step
  directory) is skipped with a message saying which step and why, and the
  previous one is tried. With ``set_aside`` (when training resumes) the
  damaged step directory is moved to ``checkpoints_damaged/`` beside it, so
  that the step can be saved again; nothing is deleted.
  """
  for step in sorted(mngr.all_steps(), reverse=True):
    # A fresh reader per attempt: a failed restore leaves a manager's item
    # handlers in a state where the next restore fails too.
    reader = ocp.CheckpointManager(
        mngr.directory, options=ocp.CheckpointManagerOptions(read_only=True))
    try:
      state = restore(reader, step, target)
      reader.close()
      return state, step
    except Exception as e:  # orbax/TensorStore raise many types.
      reader.close()
      reason = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
      log(f'warning: checkpoint step {step} in {mngr.directory} does not restore '
          f'({type(e).__name__}: {reason}); trying the previous one')
      if set_aside:
        src = os.path.join(str(mngr.directory), str(step))
        dst = os.path.join(os.path.dirname(str(mngr.directory).rstrip('/')),
                           'checkpoints_damaged', f'{step}_{int(time.time())}')
        if os.path.isdir(src):
          os.makedirs(os.path.dirname(dst), exist_ok=True)
          os.replace(src, dst)
          log(f'moved the damaged step {step} to {dst}')
        mngr.reload()
  if mngr.all_steps():
    raise FileNotFoundError(f'{mngr.directory}: no saved checkpoint restores '
                            f'(steps {sorted(mngr.all_steps())})')
  return target, None


def save_angles(workdir: str, angles):
  import numpy as np
  os.makedirs(workdir, exist_ok=True)
  tmp = os.path.join(workdir, ANGLES_FILE + '.tmp.npy')
  np.save(tmp, np.asarray(angles, np.float32))
  os.replace(tmp, os.path.join(workdir, ANGLES_FILE))


def save_config(workdir: str, config):
  os.makedirs(workdir, exist_ok=True)
  with open(os.path.join(workdir, CONFIG_FILE), 'w') as f:
    f.write(config.to_json(indent=2))


def load_config(workdir: str) -> ml_collections.ConfigDict:
  path = os.path.join(workdir, CONFIG_FILE)
  if not os.path.isfile(path):
    raise FileNotFoundError(f'{path}: not a training run directory (no '
                            f'{CONFIG_FILE}); train one with '
                            '`python -m dusty_jax.train --workdir DIR`')
  with open(path) as f:
    return ml_collections.ConfigDict(json.load(f))


def load_checkpoint(workdir: str, step: int | None = None, ema: bool = True,
                    config: str | None = None, angles: str | None = None):
  """(GeneratorParams, config) of a training run: the EMA generator by default.

  Everything ``sample`` and ``invert`` need: the generator's variables, the
  run's sensor and model, and the dataset's angle table. ``workdir`` may
  also be one of the authors' ``.pth`` checkpoints (see authors.py), with
  ``config`` their yaml (default: found beside it) and optional ``angles``.
  """
  if os.path.isfile(workdir):
    if step is not None:
      raise ValueError(f'{workdir}: step= is for a run directory, not a single file')
    from dusty_jax import authors
    return authors.load(workdir, config=config, ema=ema, angles=angles)
  if config is not None or angles is not None:
    raise ValueError(f'{workdir}: config= and angles= are for an authors\' .pth; '
                     'a run directory holds its own')
  from dusty_jax import sensor as sensor_lib, trainer
  from dusty_jax.data import arrays, pipeline
  config = load_config(workdir)
  sensor = sensor_lib.from_config(config.sensor)
  setup = trainer.make_setup(config, sensor)
  target = trainer.init_state(setup, jax.random.key(0))
  mngr = manager(workdir, keep=config.keep_checkpoints)
  if step is None:
    state, step = restore_latest(mngr, target)
    if step is None:
      raise FileNotFoundError(f'{workdir}: no checkpoint saved yet')
  elif step not in mngr.all_steps():
    raise FileNotFoundError(f'{workdir}: no checkpoint of step {step}; saved '
                            f'steps: {sorted(mngr.all_steps())}')
  else:
    state = restore(mngr, step, target)
  if os.path.isfile(os.path.join(workdir, ANGLES_FILE)):
    # Written by training at its start: a copied run needs no dataset.
    angles = arrays.load_angles(workdir, sensor)
  else:  # runs written before the run kept its own angle table
    try:
      angles = arrays.load_angles(pipeline.dataset_dir(config, sensor, log=lambda m: None),
                                  sensor)
    except FileNotFoundError:
      angles = sensor.nominal_angles()
  tolerance = config.get('tolerance', 0.0)
  variables = state.ema_params if ema else state.g_params
  return trainer.generator_bundle(setup, variables, angles, tolerance), config
