"""A tiny deterministic training run shared by the parallelism tests, and
the experiment files as the tests read them."""

import os
import runpy

import jax
import numpy as np

from dusty_jax import parallel, trainer
from dusty_jax.sensor import tiny_sensor

EXPERIMENTS = os.path.join(os.path.dirname(__file__), '..', 'experiments')


def experiment(name: str) -> dict:
  """The globals of experiments/NAME.py."""
  return runpy.run_path(os.path.join(EXPERIMENTS, f'{name}.py'))


# The study's recipe: study(model, preset, scale), PRESETS, SCALES, DIPS, ...
STUDY = experiment('study')


def tiny_config(**overrides):
  c = experiment('smoke')['get_config']()
  c.r1_every = 1
  for k, v in overrides.items():
    setattr(c, k, v)
  return c


def fixed_batches(config, sensor, num_steps, drop_rates=None):
  """Uniform scans; with ``drop_rates`` (one per example), that fraction of
  each example's pixels is dropped (set to the drop constant)."""
  rng = np.random.default_rng(123)
  out = []
  for _ in range(num_steps):
    x = rng.uniform(-1, 1, (config.batch_size,) + sensor.shape).astype(np.float32)
    if drop_rates is not None:
      rates = np.asarray(drop_rates, np.float32)[:, None, None]
      x[rng.uniform(size=x.shape) < rates] = -1.0
    out.append(x)
  return out


def run_steps(num_steps=2, devices=None, config=None, drop_rates=None):
  """Trains ``num_steps`` on fixed batches (fixed_batches); returns the host
  params pytree."""
  config = config or tiny_config()
  sensor = tiny_sensor(config.sensor.height, config.sensor.width)
  setup = trainer.make_setup(config, sensor)
  mesh = parallel.data_mesh(devices)
  step = parallel.data_parallel(trainer.step_fn(setup), mesh)
  state = parallel.replicate(trainer.init_state(setup, jax.random.key(0)), mesh)
  local = parallel.local_batch_size(config.batch_size, mesh)
  lo = jax.process_index() * local
  for batch in fixed_batches(config, sensor, num_steps, drop_rates):
    state, _ = step(state, parallel.shard_batch(batch[lo:lo + local], mesh),
                    jax.random.key(1))
  return parallel.to_host({'g': state.g_params, 'd': state.d_params,
                           'ema': state.ema_params})


def run_with_metrics(num_steps=3, devices=None, config=None, drop_rates=None):
  """As :func:`run_steps`, also returning each step's metrics (host floats)
  and the initial params: (init params, final params, [metrics])."""
  config = config or tiny_config()
  sensor = tiny_sensor(config.sensor.height, config.sensor.width)
  setup = trainer.make_setup(config, sensor)
  mesh = parallel.data_mesh(devices)
  step = parallel.data_parallel(trainer.step_fn(setup), mesh)
  state = parallel.replicate(trainer.init_state(setup, jax.random.key(0)), mesh)
  host = lambda s: parallel.to_host({'g': s.g_params, 'd': s.d_params, 'ema': s.ema_params})
  init, records = host(state), []
  for batch in fixed_batches(config, sensor, num_steps, drop_rates):
    state, metrics = step(state, parallel.shard_batch(batch, mesh), jax.random.key(1))
    records.append({k: float(v) for k, v in parallel.to_host(metrics).items()})
  return init, host(state), records
