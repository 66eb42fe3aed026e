"""Where a run's MMD lives: Table II's point metrics with the far returns dropped.

    python benchmarks/research/drops/far_returns.py --runs NAME=RUN,... [--far 40] [--num 200]
        [--points 512] [--seeds 2] [--out benchmarks/research/drops/results --name far_returns]

For each run, samples as evaluation.synthesis does (the same sampling keys)
and scores COV, MMD and JSD against the test split twice: as sampled, and
with every generated return beyond ``--far`` metres turned into a drop (the
test clouds are left as they are). If a run's MMD falls to the others' level
once its far returns are gone, what separates it is the far structure of its
scenes, not the near one. A diagnosis, not a metric: dropping points changes
the clouds that farthest point sampling draws from, so COV and JSD move too.
Also prints the share of returns beyond ``--far`` in the samples and in the
test scans. Writes ``NAME.json``.
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import numpy as np

# benchmarks/ holds common.py, shared with the product benchmarks.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..'))
import common
from dusty_jax import codec, evaluation, generator, sampling
from dusty_jax.data import arrays, pipeline
from dusty_jax.metrics import protocol

HERE = os.path.dirname(os.path.abspath(__file__))


def far_share(x, far_x: float) -> float:
  """Share of the returns of ``x`` (normalised inverse depth) beyond the
  value ``far_x`` (farther = smaller inverse depth)."""
  valid = x > codec.ALPHA
  return float((x[valid] < far_x).mean())


def score(run: str, a) -> dict:
  params, config = generator.load(run, log=lambda *_: None)
  sensor = params.sensor
  d = pipeline.dataset_dir(config, sensor, log=lambda *_: None)
  ref = evaluation.encoded_subset(arrays.load_split(d, 'test', sensor), a.num, 'reference',
                                  sensor)
  far_x = float(codec.encode(np.full((1, 1, 1), a.far, np.float32), sensor)[0, 0, 0])
  out = {'far_share': [], 'test_far_share': far_share(ref, far_x)}
  for cut in ('as_sampled', 'far_dropped'):
    out[cut] = {k: [] for k in ('cov', 'mmd', 'jsd')}
  for seed in range(a.seeds):
    fake = np.asarray(sampling.sample_scans(
        params, jax.random.key(evaluation.SAMPLE_SEED + seed), len(ref)))
    out['far_share'].append(far_share(fake, far_x))
    for cut, x in (('as_sampled', fake),
                   ('far_dropped', np.where(fake < far_x, codec.ALPHA, fake))):
      m = protocol.compare(ref, x.astype(np.float32), params.angles, sensor=sensor,
                           protocol='reference', num_points=a.points, seed=seed,
                           tolerance=0.0, cache={})
      for k in out[cut]:
        out[cut][k].append(float(m[k]))
  return out


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--runs', required=True, help='NAME=RUN_DIR,...')
  p.add_argument('--far', type=float, default=40.0, help='metres')
  p.add_argument('--num', type=int, default=200)
  p.add_argument('--points', type=int, default=512)
  p.add_argument('--seeds', type=int, default=2, help='sampling seeds per run')
  p.add_argument('--out', default=os.path.join(HERE, 'results'))
  p.add_argument('--name', default='far_returns')
  a = p.parse_args(argv)
  runs = dict(item.split('=', 1) for item in a.runs.split(',') if item)
  common.print_banner()
  results = {}
  print(f'test split, N = {a.num}, {a.points} points, {a.seeds} sampling seeds; far = beyond '
        f'{a.far:g} m')
  print(f'{"run":28s}{"far share":>10s} | as sampled: {"COV %":>7s}{"MMD x1e3":>9s}'
        f'{"JSD x1e2":>9s} | far dropped: {"COV %":>7s}{"MMD x1e3":>9s}{"JSD x1e2":>9s}')
  for name, run in runs.items():
    r = results[name] = dict(run=run, **score(run, a))
    s, f = r['as_sampled'], r['far_dropped']
    print(f'{name:28s}{np.mean(r["far_share"]):10.3f} | {"":12s}{1e2 * np.mean(s["cov"]):7.1f}'
          f'{1e3 * np.mean(s["mmd"]):9.2f}{1e2 * np.mean(s["jsd"]):9.1f} | {"":13s}'
          f'{1e2 * np.mean(f["cov"]):7.1f}{1e3 * np.mean(f["mmd"]):9.2f}'
          f'{1e2 * np.mean(f["jsd"]):9.1f}', flush=True)
  print(f'test scans: far share {next(iter(results.values()))["test_far_share"]:.3f}')
  path = common.write_json(os.path.join(a.out, f'{a.name}.json'),
                           dict(far_m=a.far, num=a.num, points=a.points, seeds=a.seeds,
                                results=results))
  print(f'saved {path}')


if __name__ == '__main__':
  main()
