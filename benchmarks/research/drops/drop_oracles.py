"""What measurability scores mean: reference maps scored like a model's.

    python benchmarks/research/drops/drop_oracles.py [--num 64]
        [--out benchmarks/research/drops/results/drop_oracles.json]

The study scores a model's measurability against the simulated test scans'
observed returns (benchmarks/study.py, ``disentangle``). Three maps that use
no model are scored here by the same function
(``ground_truth.measurability_scores``), on the same first ``--num`` test
scans of the study's data:

  * ``truth``: the simulator's true keep probability, 1 - drop_prob: the
    best any model can do;
  * ``ring rate``: each ring's keep rate over the training split's observed
    scans, the same at every pixel of a ring: what a per-ring rate alone
    scores;
  * ``ring x depth rate``: each (ring, depth bin) cell's keep rate over the
    training split, the bins of drops.RATE_DEPTH_EDGES judged on the
    complete depth (which a generator draws as x_tilde): what the drops
    variant's rate term asks for, and nothing within a cell.

A model's AUC says where its drops go only as far as it beats these.

    python benchmarks/research/drops/drop_oracles.py --runs NAME=RUN_DIR,... [--out ...]

also splits a model's shortfall in two, on the test scans whose inversion
the study saved (``RUN_DIR/study_inversion.npz``: the first 8, inverted
500 iterations): its measurability as inverted, against the cell rates at
the depth bins of its own inverted x_tilde. If the cell rates at its own
depth place the drops well, the head is what misses; if not, the depth.
Every map is then scored on those 8 scans only. With ``--invert-steps N
[--init encoder]`` each run's generator inverts the first ``--num`` test
scans itself instead (evaluation.restore_batches, seed 0 as in the study):
does a longer search, or the encoder's start, find a depth that places the
drops better?
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

# benchmarks/ holds common.py, shared with the product benchmarks.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..'))
import common
import dusty_jax
from dusty_jax import codec, configs, drops, evaluation
from dusty_jax.data import arrays, pipeline
from dusty_jax.metrics import ground_truth
from dusty_jax.sensor import get_sensor

HERE = os.path.dirname(os.path.abspath(__file__))


def cell_sums(values, depth, sensor, edges):
  """(sum of ``values``, pixel count), each (H, len(edges) + 1), over the
  surface pixels of ``depth`` (B, H, W metres) by ring and depth bin."""
  h, nb = depth.shape[1], len(edges) + 1
  surface = np.asarray(codec.valid_depth(depth, sensor))
  cell = np.broadcast_to(np.arange(h)[None, :, None] * nb + np.digitize(depth, edges),
                         depth.shape)[surface]
  sums = np.bincount(cell, np.asarray(values, np.float64)[surface], minlength=h * nb)
  return sums.reshape(h, nb), np.bincount(cell, minlength=h * nb).reshape(h, nb)


def cell_rates(observed, complete, sensor, edges):
  """(rates, counts): the (H, len(edges) + 1) keep rate of the observed
  returns per ring and bin of the complete depth, over surface pixels (1 for
  a cell with none), and each cell's surface pixels."""
  kept, n = cell_sums(codec.valid_depth(observed, sensor), complete, sensor, edges)
  return np.where(n > 0, kept / np.maximum(n, 1), 1.0), n


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--num', type=int, default=64, help='test scans, as the study inverts')
  p.add_argument('--runs', default='', help="NAME=RUN_DIR,...: score the study's inversions")
  p.add_argument('--invert-steps', type=int, default=0,
                 help="invert with each run's generator (0: read the study's inversion)")
  p.add_argument('--init', default='random', choices=('random', 'encoder'))
  p.add_argument('--out', default=os.path.join(HERE, 'results', 'drop_oracles.json'))
  a = p.parse_args(argv)
  runs = dict(item.split('=', 1) for item in a.runs.split(',') if item)
  saved = {}
  if not a.invert_steps:
    for run in runs.values():
      if not os.path.isfile(os.path.join(run, 'study_inversion.npz')):
        raise SystemExit(f'error: {run}/study_inversion.npz: no such file (benchmarks/'
                         'study.py writes it when it evaluates a run; or use --invert-steps)')
    saved = {name: np.load(os.path.join(run, 'study_inversion.npz'))
             for name, run in runs.items()}
    if saved:
      a.num = min(len(v['measurability']) for v in saved.values())
  common.print_banner()
  config = configs.study('dusty1')
  sensor = get_sensor(config.sensor.preset)
  d = pipeline.dataset_dir(config, sensor, log=print)
  load = lambda split, kind='': np.asarray(arrays.load_split(d, split, sensor, kind),
                                           np.float64)
  obs, comp, prob = (load('test', k)[:a.num] for k in ('', 'complete', 'drop_prob'))
  for name, run in runs.items() if a.invert_steps else ():
    params = dusty_jax.load_checkpoint(run)[0]
    res = [b[4] for b in evaluation.restore_batches(
        params, obs, num_steps=a.invert_steps, init=a.init, progress=True,
        desc=f'{name}: inverting')]
    saved[name] = {k: np.concatenate([r[k] for r in res])
                   for k in ('inv_depth', 'measurability')}
  train_obs, train_comp = load('train'), load('train', 'complete')
  edges = np.asarray(drops.RATE_DEPTH_EDGES)
  ring = drops.ring_keep_rate(train_obs, sensor, num=len(train_obs))
  cells, _ = cell_rates(train_obs, train_comp, sensor, edges)
  rows = np.arange(obs.shape[1])[None, :, None]
  maps = {
      'truth': 1.0 - prob,
      'ring rate': np.broadcast_to(ring[None, :, None], obs.shape),
      'ring x depth rate': cells[rows, np.digitize(comp, edges)],
  }
  for name, inv in saved.items():
    depth = np.asarray(codec.complete_depth(inv['inv_depth'][:a.num], sensor), np.float64)
    maps[f'{name}: as inverted'] = inv['measurability'][:a.num]
    maps[f'{name}: cell rates at its depth'] = cells[rows, np.digitize(depth, edges)]
  out = {}
  print(f'\n{a.num} test scans; surfaces nearer than {ground_truth.NEAR_M:.0f} m for the '
        '"near" columns')
  width = max(len(n) for n in maps) + 2
  print(f'{"map":{width}s}{"AUC":>8s}{"AUC near":>10s}{"within rings":>14s}{"ECE":>8s}')
  for name, m in maps.items():
    s = ground_truth.measurability_scores(sensor, m, obs, comp, prob)
    out[name] = {k: s[k] for k in ('auc', 'auc_near', 'auc_near_within_ring', 'ece')}
    print(f'{name:{width}s}{s["auc"]:8.3f}{s["auc_near"]:10.3f}'
          f'{s["auc_near_within_ring"]:14.3f}{s["ece"]:8.3f}')
  common.write_json(a.out, dict(num=a.num, runs=runs, invert_steps=a.invert_steps,
                                init=a.init, near_m=ground_truth.NEAR_M,
                                depth_edges_m=edges.tolist(), scores=out))
  print(f'wrote {a.out}')


if __name__ == '__main__':
  main()
