"""Where a drops variant's synthesis scores come from: its samples with their
drops, and the same samples with every point kept.

    python benchmarks/research/drops/drops_cov.py [--models sim-dusty1,sim-dusty1-authors]
        [--seeds 3]
    python benchmarks/research/drops/drops_cov.py --models RUN_DIR,... [--no-keep-all]

Table II (the study's N, points and seeds) of each generator (a shipped name
or a training run's directory) twice:
as it samples, and with its measurability forced to 1 (the pixel logit's bias
set to +50 and its ring offsets to 0, so the Gumbel mask keeps every pixel),
which leaves x_tilde, the scene, as it is. If the kept-all row scores as the
faithful DUSty-I does, what a variant loses in Table II comes from where its
drops fall; if not, from the scene its trunk draws.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

# benchmarks/ holds common.py, shared with the product benchmarks.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..'))
import common

HERE = os.path.dirname(os.path.abspath(__file__))
KEEP_ALL_LOGIT = 50.0


def keep_all(params):
  """``params`` with a measurability of 1 everywhere (x_tilde unchanged)."""
  from dusty_jax import drops
  v = drops.set_mask_bias(params.variables, KEEP_ALL_LOGIT)
  if 'ring_bias' in v['params']:
    v['params']['ring_bias'] = v['params']['ring_bias'] * 0.0
  return params.replace(variables=v)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--models', default='sim-dusty1,sim-dusty1-authors')
  p.add_argument('--num', type=int, default=200)
  p.add_argument('--points', type=int, default=512)
  p.add_argument('--seeds', type=int, default=3)
  p.add_argument('--no-keep-all', action='store_true',
                 help='score the generators as they sample only')
  p.add_argument('--out', default=os.path.join(HERE, 'results', 'drops_cov.json'))
  a = p.parse_args(argv)
  import dusty_jax
  from dusty_jax import configs, evaluation
  from dusty_jax.data import arrays, pipeline
  common.print_banner()
  config = configs.study('dusty1')
  rows = {}
  data = None
  for name in [m for m in a.models.split(',') if m]:
    params = (dusty_jax.load_checkpoint(name)[0] if os.path.isdir(name)
              else dusty_jax.load_pretrained(name))
    if not params.variant.has_measurability and not a.no_keep_all:
      raise SystemExit(f'{name}: the {params.model} model has no measurability to force')
    if data is None:
      d = pipeline.dataset_dir(config, params.sensor, log=print)
      data = {s: np.asarray(arrays.load_split(d, s, params.sensor)) for s in ('test', 'train')}
    runs = [(name, params)]
    if not a.no_keep_all:
      runs.append((f'{name}, every point kept', keep_all(params)))
    for label, prm in runs:
      rec = evaluation.synthesis(prm, data['test'], data['train'] if not rows else None,
                                 num=a.num, points=a.points, seeds=a.seeds, progress=True)
      for row, metrics in rec['rows'].items():
        key = label if row != evaluation.TRAINING_ROW else row
        rows[key] = {k: [float(v) for v in vals] for k, vals in metrics.items()}
      print(f'{label}: ' + ', '.join(
          f'{k} {np.mean(v):.4g} +- {np.std(v):.2g}'
          for k, v in rows[label].items()), flush=True)
  common.write_json(a.out, dict(num=a.num, points=a.points, seeds=a.seeds, rows=rows))


if __name__ == '__main__':
  main()
