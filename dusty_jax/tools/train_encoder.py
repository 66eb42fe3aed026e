"""Trains the encoder that starts GAN inversion, for one trained generator.

    python -m dusty_jax.tools.train_encoder --workdir RUN [--steps 600] [--batch 32]

Reads the run's EMA generator (frozen), trains an encoder (encoder_trainer.train) on
the generator's own samples with random corruptions, checkpoints into
``RUN/encoder/`` (a rerun resumes there) and writes ``RUN/encoder.npz``,
which ``load_checkpoint(RUN)`` then attaches, so that
``invert(params, scan, init='encoder')`` and ``invert --init encoder``
work. ``--export NAME.npz`` also writes generator + encoder as one file.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
from absl import flags

from dusty_jax import tools


def main(argv=None):
  from dusty_jax.encoder_trainer import TrainOptions  # its defaults are the flags' defaults
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
  """encoder_trainer.train on the run ``workdir``'s generator; writes RUN/encoder.npz
  (and ``export``). Returns what was written."""
  # The library (and JAX) load once the flags are good.
  from dusty_jax import encoder, encoder_trainer, generator, pretrained

  if not os.path.exists(workdir) and workdir not in pretrained.available():
    raise FileNotFoundError(f'{workdir}: no such run directory')
  if not os.path.isdir(workdir):
    raise FileNotFoundError(f'{workdir}: not a training run directory (a pretrained '
                            'model or an exported .npz holds no training state to add '
                            'an encoder to)')
  params, config = generator.load(workdir)
  real = _training_scans(workdir, config, params.sensor) if opts.w_real > 0 else None
  settings = encoder.EncoderSettings()
  enc_vars, info = encoder_trainer.train(params, os.path.join(workdir, encoder_trainer.DIRECTORY),
                                         opts, real, settings)
  path = generator.save_encoder(os.path.join(workdir, generator.ENCODER_FILE), enc_vars,
                                settings, info)
  if export:
    generator.export(params.replace(encoder=enc_vars, encoder_settings=settings), export,
                     source=f'{os.path.abspath(workdir)} + encoder ({opts.steps} steps)')
    path = f'{path} and {export}'
  return path


if __name__ == '__main__':
  main()
