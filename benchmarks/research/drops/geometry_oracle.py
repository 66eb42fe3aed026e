"""How far depth alone can place drops within rings: tables on the complete depth.

    python benchmarks/research/drops/geometry_oracle.py [--train 500] [--num 200] [--split val]

Issue 37 asks for a within-ring AUC (surfaces < 40 m) of 0.70. A generator's
measurability sees only its own complete depth x_tilde, so the question is
what a map that is a function of the depth image can score. Keep-rate
tables fitted on ``--train`` training scans, on the simulator's *complete*
depth (what a perfect generator would draw), scored on ``--num`` scans of
``--split`` against their observed returns by the library's
``ground_truth.measurability_scores``:

  * ``ring``: each ring's keep rate (the per-ring table);
  * ``ring x depth``: per (ring, depth bin), the bins of drops.RATE_DEPTH_EDGES
    (what the levels fit per cell);
  * ``ring x depth x incidence``: also by the cosine of the incidence angle,
    from the surface normal of the depth image's 3-D points (central
    differences), with pixels on a depth edge (a neighbour without a return,
    or one in the same ring more than 10 % away) in a bin of their own;
  * ``truth``: the simulator's keep probability (its material is what depth
    cannot see: glass, paint, foliage).

A cell with fewer than ``--min-pixels`` training pixels takes its coarser
table's rate. Writes ``--out`` (JSON).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, '..', '..'))  # benchmarks/common.py

import common  # noqa: E402
from dusty_jax import codec, configs, drops  # noqa: E402
from dusty_jax.data import arrays, pipeline, simulated_lidar  # noqa: E402
from dusty_jax.metrics import ground_truth  # noqa: E402
from dusty_jax.sensor import get_sensor  # noqa: E402

COS_EDGES = np.array([0.2, 0.4, 0.6, 0.8, 0.9])
EDGE_JUMP = 0.1  # relative depth step to a neighbour that makes a depth edge


def incidence_bins(depth, sensor):
  """(B, H, W) bin of each pixel's incidence cosine (0 .. len(COS_EDGES)),
  len(COS_EDGES) + 1 on a depth edge."""
  dirs = simulated_lidar.ray_directions(sensor)            # (H, W, 3)
  p = depth[..., None] * dirs
  du = np.roll(p, -1, axis=2) - np.roll(p, 1, axis=2)      # along the ring (wraps)
  dv = np.zeros_like(p)
  dv[:, 1:-1] = p[:, 2:] - p[:, :-2]                       # across rings
  n = np.cross(du, dv)
  norm = np.linalg.norm(n, axis=-1)
  cos = np.abs(np.einsum('bhwk,hwk->bhw', n, dirs)) / np.maximum(norm, 1e-12)
  bins = np.digitize(cos, COS_EDGES)
  along = [np.roll(depth, s, axis=2) for s in (-1, 1)]
  across = [np.concatenate([depth[:, :1], depth[:, :-1]], 1),
            np.concatenate([depth[:, 1:], depth[:, -1:]], 1)]
  # A depth edge: a neighbour without a return, or a step along the ring
  # (across rings, ground seen at a grazing angle steps by more than 10 %
  # beyond about 25 m: that is the incidence the bins are for).
  edge = (norm == 0) | (depth <= 0)
  for q in along + across:
    edge |= q <= 0
  for q in along:
    edge |= np.abs(q - depth) > EDGE_JUMP * depth
  edge[:, 0] = edge[:, -1] = True
  return np.where(edge, len(COS_EDGES) + 1, bins)


def cells(depth, sensor, with_incidence):
  """(B, H, W) integer cell of each pixel: ring, depth bin[, incidence bin]."""
  edges = np.asarray(drops.RATE_DEPTH_EDGES)
  b, h, w = depth.shape
  ring = np.broadcast_to(np.arange(h)[None, :, None], depth.shape)
  cell = ring * (len(edges) + 1) + np.digitize(depth, edges)
  if with_incidence:
    cell = cell * (len(COS_EDGES) + 2) + incidence_bins(depth, sensor)
  return cell


def fit(cell, keep, surface, size):
  total = np.bincount(cell[surface], keep[surface], minlength=size)
  count = np.bincount(cell[surface], minlength=size)
  return total, count


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  p.add_argument('--train', type=int, default=500, help='training scans the tables are fitted on')
  p.add_argument('--num', type=int, default=200, help='scans scored')
  p.add_argument('--split', default='val', choices=('val', 'test'))
  p.add_argument('--min-pixels', type=int, default=50)
  p.add_argument('--out', default=os.path.join(HERE, 'results', 'geometry_oracle.json'))
  a = p.parse_args(argv)
  config = configs.study('dusty1')
  sensor = get_sensor(config.sensor.preset)
  d = pipeline.dataset_dir(config, sensor, log=print)
  load = lambda split, n, kind='': np.asarray(arrays.load_split(d, split, sensor, kind)[:n],
                                              np.float64)
  tr_obs, tr_comp = load('train', a.train), load('train', a.train, 'complete')
  obs, comp, prob = (load(a.split, a.num, k) for k in ('', 'complete', 'drop_prob'))
  tr_surface = np.asarray(codec.valid_depth(tr_comp, sensor))
  tr_keep = np.asarray(codec.valid_depth(tr_obs, sensor)).astype(np.float64)
  surface = np.asarray(codec.valid_depth(comp, sensor))
  h = sensor.height
  n_depth = len(drops.RATE_DEPTH_EDGES) + 1
  n_cos = len(COS_EDGES) + 2
  # Coarse to fine: ring, ring x depth, ring x depth x incidence.
  ring_rate = ground_truth.ring_keep_rate(tr_obs, sensor)
  maps = {'ring': np.broadcast_to(ring_rate[None, :, None], comp.shape)}
  coarse = maps['ring']
  for name, inc, size in (('ring x depth', False, h * n_depth),
                          ('ring x depth x incidence', True, h * n_depth * n_cos)):
    total, count = fit(cells(tr_comp, sensor, inc), tr_keep, tr_surface, size)
    rate = total / np.maximum(count, 1)
    c = cells(comp, sensor, inc)
    maps[name] = np.where(count[c] >= a.min_pixels, rate[c], coarse)
    coarse = maps[name]
  maps['truth'] = 1.0 - prob
  record = {'machine': common.machine(), 'split': a.split, 'num': a.num, 'train': a.train,
            'min_pixels': a.min_pixels, 'cos_edges': COS_EDGES.tolist(), 'maps': {}}
  for name, m in maps.items():
    s = ground_truth.measurability_scores(sensor, np.where(surface, m, 0.0), obs, comp, prob)
    s.pop('reliability')
    record['maps'][name] = s
    print(f'{name:28s} AUC<40 {s["auc_near"]:.3f} within rings {s["auc_near_within_ring"]:.3f} '
          f'ECE {s["ece"]:.3f}', flush=True)
  os.makedirs(os.path.dirname(a.out), exist_ok=True)
  with open(a.out, 'w') as f:
    json.dump(record, f, indent=1)
  print(f'wrote {a.out}')


if __name__ == '__main__':
  main()
