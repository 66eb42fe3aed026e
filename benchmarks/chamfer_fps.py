"""Chamfer-matrix pairs per second and farthest-point-sampling time.

    python benchmarks/chamfer_fps.py [--points 2048] [--clouds 64]

Chamfer: an (n x n) matrix between two sets of random clouds of --points
points each, reported as pairs per second (median of --repeats). FPS: 2048
of 16384 points (a 64x256 scan), ms per cloud, one cloud at a time and
vmapped over a batch. Results go to benchmarks/results/chamfer_fps.json.
"""

import argparse
import os

import numpy as np

import common
from dusty_jax.metrics import chamfer, clouds


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--points', type=int, default=2048)
  p.add_argument('--clouds', type=int, default=64)
  p.add_argument('--tile', type=int, default=8)
  p.add_argument('--repeats', type=int, default=5)
  p.add_argument('--fps-batch', type=int, default=64)
  p.add_argument('--out', default=os.path.join(os.path.dirname(__file__), 'results',
                                               'chamfer_fps.json'))
  a = p.parse_args()
  rng = np.random.default_rng(0)
  n = a.clouds
  A = rng.normal(size=(n, a.points, 3)).astype(np.float32)
  B = rng.normal(size=(n, a.points, 3)).astype(np.float32)
  info = common.print_banner()
  med = common.timed(lambda: chamfer.pairwise(A, B, tile=a.tile), a.repeats).median
  pairs = n * n / med
  print(f'chamfer {a.points} pts: {n}x{n} matrix in {med:.2f} s -> {pairs:.0f} pairs/s '
        f'(tile {a.tile}, median of {a.repeats})')
  med_sym = common.timed(lambda: chamfer.pairwise(A, tile=a.tile), a.repeats).median
  print(f'chamfer symmetric {n}x{n}: {med_sym:.2f} s ({n * n / med_sym:.0f} '
        'effective pairs/s, each unordered pair once)')

  pts = rng.normal(size=(a.fps_batch, 16384, 3)).astype(np.float32)
  valid = rng.uniform(size=(a.fps_batch, 16384)) > 0.2
  one = lambda: clouds.farthest_point_indices(pts[:1], valid[:1], 2048)
  med_one = common.timed(one, a.repeats).median
  many = lambda: clouds.farthest_point_indices(pts, valid, 2048)
  med_many = common.timed(many, a.repeats).median
  print(f'FPS 2048 of 16384: {med_one * 1e3:.1f} ms for one cloud, '
        f'{med_many / a.fps_batch * 1e3:.1f} ms per cloud in a batch of {a.fps_batch}')
  common.write_json(a.out, dict(
      points=a.points, clouds=n, tile=a.tile, chamfer_pairs_per_s=pairs,
      chamfer_matrix_s=med, chamfer_sym_s=med_sym, fps_one_ms=med_one * 1e3,
      fps_batched_ms=med_many / a.fps_batch * 1e3, device=info['device_kind'],
      cpus=info['cpus']))


if __name__ == '__main__':
  main()
