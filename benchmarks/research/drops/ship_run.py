"""Ships a training run as a pretrained model (dusty_jax/pretrained/NAME.npz).

The run's EMA generator as ``load_checkpoint`` gives it: with its drop levels
(``depth_levels.npz``, config ``drops.depth_levels``) and its encoder
(``encoder.npz``, tools/train_encoder) where the run has them. The file's
``training`` record names the config, seed, steps, drops options and the
encoder's options, as benchmarks/study.py's ``--export`` does.

    python benchmarks/research/drops/ship_run.py --workdir RUN --name sim-dusty1 \
        --config experiments/synthetic.py
"""

from __future__ import annotations

import argparse
import json
import os


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  p.add_argument('--workdir', required=True, help='a finished training run')
  p.add_argument('--name', required=True, help='the pretrained name to write')
  p.add_argument('--config', required=True, help='the config file that trained it')
  p.add_argument('--note', default='', help='where and how it ran (kept in the source)')
  a = p.parse_args(argv)
  import dusty_jax
  from dusty_jax import configs, pretrained
  params, config = dusty_jax.load_checkpoint(a.workdir)
  drops = config.drops.to_dict()
  training = {'config': a.config, 'scale': 'cpu' if config.batch_size == 16 else 'paper',
              'seed': int(config.seed), 'steps': int(config.num_steps),
              'batch_size': int(config.batch_size), 'augment': config.augment,
              'drops': drops,
              'beyond_the_paper': drops != configs.drop_defaults().to_dict()}
  source = a.config + (f' ({a.note})' if a.note else '')
  if params.settings.depth_levels:
    training['depth_levels'] = ('dusty_jax.evaluation.fit_levels at the end of training: '
                                'inversions of the first 256 training scans, 300 iterations '
                                'from a random start, seed 0')
    source += ' + depth levels'
  options = os.path.join(a.workdir, 'encoder', 'options.json')
  if params.encoder is not None and os.path.isfile(options):
    with open(options) as f:
      opts = json.load(f)
    training['encoder'] = ('python -m dusty_jax.tools.train_encoder --workdir RUN ' +
                           ' '.join(f'--{k}={v}' for k, v in opts.items()))
    source += ' + encoder'
  path = pretrained.export(params, a.name, source=source, training=training)
  print(f'wrote {path} ({os.path.getsize(path) / 1e6:.2f} MB)')


if __name__ == '__main__':
  main()
