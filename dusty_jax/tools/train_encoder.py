"""Trains the encoder that starts GAN inversion, for one trained generator.

    python -m dusty_jax.tools.train_encoder --workdir RUN [--steps 3000] [--batch 32]

Reads the run's EMA generator (frozen), trains an encoder (encoder.py) on
the generator's own samples with random corruptions, checkpoints into
``RUN/encoder/`` (a rerun resumes there) and writes ``RUN/encoder.npz``,
which ``load_checkpoint(RUN)`` then attaches, so that
``invert(params, scan, init='encoder')`` and ``invert --init encoder``
work. ``--export NAME.npz`` also writes generator + encoder as one file.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time

import numpy as np
from absl import flags

from dusty_jax import tools

OPTIONS_FILE = 'options.json'
SAVE_EVERY = 250


def main(argv=None):
  from dusty_jax.encoder import TrainOptions  # its defaults are the flags' defaults
  d = TrainOptions()
  f = flags.FlagValues()
  flags.DEFINE_string('workdir', None, 'training run directory', flag_values=f,
                      required=True)
  flags.DEFINE_integer('steps', d.steps, 'Adam steps', lower_bound=1, flag_values=f)
  flags.DEFINE_integer('batch', d.batch, 'samples per step', lower_bound=1,
                       flag_values=f)
  flags.DEFINE_float('lr', d.lr, 'peak learning rate (cosine decay)', lower_bound=0,
                     flag_values=f)
  flags.DEFINE_float('w_latent', d.w_latent, 'weight of |E(x) - z|^2 / d',
                     lower_bound=0, flag_values=f)
  flags.DEFINE_float('w_rec', d.w_rec, 'weight of the L1 of x_tilde through G',
                     lower_bound=0, flag_values=f)
  flags.DEFINE_float('w_real', d.w_real, "weight of the inversion's objective on the "
                     "run's training scans (0: G's samples only)", lower_bound=0,
                     flag_values=f)
  flags.DEFINE_integer('real_batch', d.real_batch, 'training scans per step',
                       lower_bound=1, flag_values=f)
  flags.DEFINE_float('max_drop', d.max_drop, 'largest share of points a random drop '
                     'corruption removes (from 0.5)', lower_bound=0.5, upper_bound=1.0,
                     flag_values=f)
  flags.DEFINE_float('max_noise', d.max_noise, "largest std of the random range noise "
                     "(normalised inverse depth)", lower_bound=0, flag_values=f)
  flags.DEFINE_integer('seed', d.seed, 'random seed', flag_values=f)
  flags.DEFINE_string('export', '', 'also write generator + encoder as this .npz',
                      flag_values=f)
  tools.parse(f, argv, __doc__)
  # One flag per option, of the same name: a saved options.json reruns as flags.
  opts = TrainOptions(**{k: f[k].value for k in dataclasses.asdict(d)})
  path = tools.run(train, f.workdir, opts, f.export)
  print(f'wrote {path}')


def _check_options(directory: str, opts) -> None:
  """A resumed training must keep its options (the schedule depends on them)."""
  path = os.path.join(directory, OPTIONS_FILE)
  mine = dataclasses.asdict(opts)
  if os.path.isfile(path):
    with open(path) as fh:
      saved = json.load(fh)
    if saved != mine:
      diff = {k: (saved.get(k), v) for k, v in mine.items() if saved.get(k) != v}
      raise ValueError(f'{directory} holds an encoder training with other options '
                       f'(saved, given): {diff}; give the same flags to resume, or '
                       'remove that folder to start again')
  else:
    os.makedirs(directory, exist_ok=True)
    with open(path, 'w') as fh:
      json.dump(mine, fh, indent=2)


def _training_scans(workdir: str, config, sensor):
  """The run's training split, normalised inverse depth (N, H, W)."""
  # The data pipeline only when the real-scan term is on.
  from dusty_jax import codec
  from dusty_jax.data import arrays, pipeline  # (as above)
  if config is None:
    raise ValueError(f'{workdir}: no config.json naming its dataset; the real-scan '
                     'term needs it (or give --w_real 0)')
  d = pipeline.dataset_dir(config, sensor, log=lambda m: None)
  return np.asarray(codec.encode(arrays.load_split(d, 'train', sensor), sensor))


def train(workdir: str, opts, export: str = '') -> str:
  import jax
  import tqdm
  # The library (and JAX) load once the flags are good.
  from dusty_jax import checkpoint, encoder, generator

  if not os.path.isdir(workdir):
    raise FileNotFoundError(f'{workdir}: not a training run directory (an exported '
                            '.npz holds no training state to add an encoder to)')
  params, config = generator.load(workdir)
  params = params.replace(encoder=None, encoder_settings=None)
  real = _training_scans(workdir, config, params.sensor) if opts.w_real > 0 else None
  directory = os.path.join(workdir, 'encoder')
  _check_options(directory, opts)
  settings = encoder.EncoderSettings()
  k_init, key = jax.random.split(jax.random.key(opts.seed))
  enc_vars = encoder.init_variables(k_init, params, settings)
  state = {'encoder': enc_vars, 'opt': encoder.optimizer(opts).init(enc_vars)}
  mngr = checkpoint.manager(directory, keep=2)
  state, step = checkpoint.restore_latest(mngr, state)
  start = 0 if step is None else step
  params = params.replace(encoder_settings=settings)
  bar = tqdm.tqdm(total=opts.steps, initial=start, desc='encoder', unit='step',
                  file=sys.stderr)
  # Committed to the device as train_step's outputs are, so that the second
  # step does not compile again.
  enc_vars, opt_state = jax.device_put((state['encoder'], state['opt']),
                                       jax.local_devices()[0])
  t0, metrics = time.time(), {}
  for i in range(start, opts.steps):
    batch = None
    if real is not None:
      pick = np.random.default_rng((opts.seed, i)).integers(0, len(real), opts.real_batch)
      batch = real[pick]
    enc_vars, opt_state, metrics = encoder.train_step(
        params, enc_vars, opt_state, jax.random.fold_in(key, i), opts, real=batch)
    if (i + 1) % 50 == 0 or i + 1 == opts.steps:
      bar.set_postfix({k: f'{float(v):.4f}' for k, v in metrics.items()})
    if (i + 1) % SAVE_EVERY == 0 or i + 1 == opts.steps:
      checkpoint.save(mngr, i + 1, {'encoder': enc_vars, 'opt': opt_state}, force=True)
    bar.update(1)
  bar.close()
  checkpoint.wait(mngr)
  info = {'steps': opts.steps, 'options': dataclasses.asdict(opts),
          'final': {k: float(v) for k, v in metrics.items()},
          'seconds_this_call': round(time.time() - t0, 1)}
  path = encoder.save(os.path.join(workdir, encoder.FILE), jax.device_get(enc_vars),
                      settings, info)
  if export:
    generator.export(params.replace(encoder=enc_vars), export,
                     source=f'{os.path.abspath(workdir)} + encoder ({opts.steps} steps)')
    path = f'{path} and {export}'
  return path


if __name__ == '__main__':
  main()
