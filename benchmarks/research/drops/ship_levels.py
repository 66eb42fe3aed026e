"""Fits a shipped model's drop levels per (ring, depth) cell and ships it.

The generator's weights (and its encoder, if it has one) stay as they are;
dusty_jax.evaluation.fit_levels replaces its levels with ones fitted to
inversions of the first 256 scans of the default data's training split, as
the training's ``drops.depth_levels`` does at its end. The file's
``training`` record gains ``drops.depth_levels`` and how they were fitted.

    python benchmarks/research/drops/ship_levels.py --name sim-dusty2 --data-dir DIR
"""

from __future__ import annotations

import argparse


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  p.add_argument('--name', required=True, help='a shipped model (dusty_jax/pretrained)')
  p.add_argument('--data-dir', required=True, help='the default data (its training split)')
  a = p.parse_args(argv)
  from dusty_jax import evaluation, generator, pretrained
  from dusty_jax.data import arrays
  params = pretrained.load_pretrained(a.name)
  meta = generator.read_meta(pretrained.path_of(a.name))
  train = arrays.load_split(a.data_dir, 'train', params.sensor)
  fitted = evaluation.fit_levels(params, train, progress=True)
  training = dict(meta['training'])
  training['drops'] = dict(training['drops'], depth_levels=True)
  training['depth_levels'] = (
      f'dusty_jax.evaluation.fit_levels after training: inversions of the first '
      f'{evaluation.LEVEL_SCANS} training scans of {a.data_dir.rstrip("/").split("/")[-1]}, '
      f'{evaluation.LEVEL_STEPS} iterations from a random start, seed 0')
  source = meta['source'].replace(' + depth levels', '') + ' + depth levels'
  path = pretrained.export(fitted, a.name, source=source, training=training)
  print(f'wrote {path}')


if __name__ == '__main__':
  main()
