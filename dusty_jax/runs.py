"""A training run's directory as the trainer keeps it: what it records of the
run, whether a config may resume it, and what a stopped run says a rerun
resumes from.

Before its first checkpoint a run records its config as trained
(configs.FILE: the config as given, with the devices it trained on) and its
generator's description (generator.SPEC_FILE with angles.npy: what loading
it later needs, without the trainer or the data). The sensor has one record,
the spec in generator.json; the config keeps how it was named (a preset, a
file, a size), so a copy of the run needs no spec file.
"""

from __future__ import annotations

import os

import jax

from dusty_jax import checkpoint, configs, errors, generator, levels, sensor as sensor_lib
from dusty_jax.models import ModelSettings
from dusty_jax.sensor import SensorSpec


def as_trained(config):
  """The config as a run directory keeps it: with the devices it trained on
  (another device count trains to float rounding of this run)."""
  saved = config.copy_and_resolve_references()
  saved.unlock()
  saved.trained_on = {'devices': jax.device_count(), 'processes': jax.process_count(),
                      'platform': jax.default_backend()}
  return saved


def record(workdir: str, config, sensor: SensorSpec, settings: ModelSettings, angles):
  """Writes what the run in ``workdir`` is: its config as trained and its
  generator's description. A resumed run keeps the drop tolerance its
  generator.json holds (evaluate --tune may have set it since)."""
  configs.save(workdir, as_trained(config))
  tolerance = config.tolerance
  if os.path.isfile(os.path.join(workdir, generator.SPEC_FILE)):
    tolerance = generator.read_spec(workdir)[2]
  generator.save_spec(workdir, sensor, settings, angles, tolerance)


def record_given(workdir: str, config, params, settings: ModelSettings):
  """Writes what a run started from given generator weights ``params`` is
  (trainer.init_run): its config and its generator's description, and drop
  levels fitted after training (levels.py) into the run's levels file, at
  step 0. Returns the variables without those levels: what its checkpoint holds."""
  configs.save(workdir, config)
  variables = params.variables
  if params.settings.depth_levels:
    levels.save(workdir, variables['params']['depth_levels'], 0)
    variables = {**variables, 'params': {k: v for k, v in variables['params'].items()
                                         if k != 'depth_levels'}}
  generator.save_spec(workdir, params.sensor, settings, params.angles, params.tolerance)
  return variables


def check_resumable(workdir: str, config, sensor: SensorSpec):
  """Refuses, before anything is written, to resume a run whose checkpoints
  were made by another architecture: other values of configs.ARCHITECTURE,
  or a ``sensor`` (the config's) other than the spec the run recorded."""
  if not os.path.isfile(os.path.join(workdir, configs.FILE)):
    return
  run = configs.load(workdir)
  fields = [f'{k}: run has {a!r}, config has {b!r}'
            for k, (a, b) in configs.architecture_diff(run, config).items()]
  trained = generator.read_spec(workdir)[0]
  if trained.to_dict() != sensor.to_dict():
    diff = sensor_lib.first_difference(trained, sensor, ('run', 'config'),
                                       sensor_lib.DATA_FIELDS + ('mount_height', 'name'))
    fields.append(f'sensor.{diff or "spec"} (the run trained with '
                  f'{sensor_lib.source_of(run.sensor)}; the config gives '
                  f'{sensor_lib.source_of(config.sensor)})')
  if fields:
    raise configs.ConfigError(
        f'{workdir} holds a run of another architecture ({"; ".join(fields)}); its '
        'checkpoints cannot be resumed with this config. Use another --workdir, or the '
        "run's own values.")


# What a stopped run says a rerun resumes from.


def peer_lost(workdir: str, reason: str) -> str:
  """What a process whose peer is lost says (parallel.PeerWatch)."""
  steps = checkpoint.saved_steps(workdir)
  n = jax.process_count()
  then = (f'the last checkpoint is step {steps[-1]} in {workdir}; rerun all {n} '
          'processes to resume from it' if steps else
          f'no checkpoint was saved yet; rerun all {n} processes to start afresh')
  return f'a process of this run was lost ({reason}); {then}'


def interrupted(done: int, last) -> errors.Interrupted:
  """What Ctrl-C at step ``done`` says, the last checkpoint being ``last``."""
  return errors.Interrupted(
      f'interrupted at step {done}; ' +
      (f'the last checkpoint is step {last}; rerun the same command to resume'
       if last is not None else
       'no checkpoint was saved yet; rerun the same command to start afresh'))
