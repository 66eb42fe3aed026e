"""Fits a shipped model's drop levels per (ring, depth) cell and ships it.

The generator's weights (and its encoder, if it has one) stay as they are;
dusty_jax.levels.calibrate adds the offsets, fitted to the training split of
the default data (the first evaluation.RING_TABLE_SCANS scans, 256 samples,
seed 0), as the training's ``drops.depth_levels`` does at its end. The
file's ``training`` record gains ``drops.depth_levels`` and how they were fitted.

    python benchmarks/research/drops/ship_levels.py --name sim-dusty2 --data-dir DIR
"""

from __future__ import annotations

import argparse

import numpy as np


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  p.add_argument('--name', required=True, help='a shipped model (dusty_jax/pretrained)')
  p.add_argument('--data-dir', required=True, help='the default data (its training split)')
  a = p.parse_args(argv)
  from dusty_jax import evaluation, generator, levels, pretrained
  from dusty_jax.data import arrays
  params = pretrained.load_pretrained(a.name)
  if params.settings.depth_levels:
    raise SystemExit(f'{a.name} has its drop levels already')
  meta = generator.read_meta(pretrained.path_of(a.name))
  train = np.asarray(arrays.load_split(a.data_dir, 'train', params.sensor)
                     [:evaluation.RING_TABLE_SCANS])
  fitted = levels.calibrate(params, train)
  training = dict(meta['training'])
  training['drops'] = dict(training['drops'], depth_levels=True)
  training['depth_levels'] = (
      f'dusty_jax.levels.calibrate after training: the first {len(train)} training scans of '
      f'{a.data_dir.rstrip("/").split("/")[-1]}, 256 samples, seed 0')
  path = pretrained.export(fitted, a.name, source=meta['source'] + ' + depth levels',
                           training=training)
  print(f'wrote {path}')


if __name__ == '__main__':
  main()
