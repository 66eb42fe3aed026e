"""What cheaper evaluation settings cost: metric values, spread and time.

    python benchmarks/eval_tradeoff.py [--sizes 250,1000] [--points 512,2048] [--seeds 3]

On simulated HDL-64E scans: the reference set is N test scans, the
"generated" set N other simulated scans drawn afresh for each seed (a
generator that matches the data exactly, so the seed-to-seed spread is the
estimator's own noise). For each (N, points) it reports each metric's mean
and std over seeds and the seconds one evaluation takes. Settings whose
time on this CPU would exceed --budget seconds are not run; their time is
extrapolated (Chamfer work grows as N^2 and points^2) and marked so. Names
the cheapest setting whose metric means stay within the seed-to-seed spread
(2 std) of the largest setting measured. Writes JSON and a PNG plot.
"""

import argparse
import os

import numpy as np

import common
from dusty_jax import codec, writers
from dusty_jax.data import synthetic
from dusty_jax.metrics import protocol
from dusty_jax.sensor import get_sensor

METRICS = ('jsd', 'cov', 'mmd', '1nna', 'swd')


def main():
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument('--sizes', default='250,1000,5000')
  ap.add_argument('--points', default='512,2048')
  ap.add_argument('--seeds', type=int, default=3)
  ap.add_argument('--budget', type=float, default=400.0,
                  help='skip (and extrapolate) settings slower than this, s')
  ap.add_argument('--out', default=os.path.join(os.path.dirname(__file__), 'results'))
  a = ap.parse_args()
  info = common.print_banner()
  sensor = get_sensor('kitti')
  sizes = sorted(map(int, a.sizes.split(',')))
  points = sorted(map(int, a.points.split(',')))
  pool_n = max(s for s in sizes if s <= 2000) * (a.seeds + 1)
  print(f'simulating {pool_n} scans ...', flush=True)
  pool, _, _ = synthetic.simulate(pool_n, sensor, seed=7, workers=os.cpu_count() or 1)
  pool = np.asarray(codec.encode(pool, sensor))
  angles = sensor.nominal_angles()
  rows, measured = [], {}
  for n in sizes:
    for p in points:
      est = None
      if measured:
        # Extrapolate from the closest measured setting.
        (n0, p0), t0 = max(measured.items(), key=lambda kv: kv[0])
        est = t0 * (n / n0) ** 2 * (p / p0) ** 2
      if est is not None and est > a.budget or n * (a.seeds + 1) > len(pool):
        rows.append(dict(n=n, points=p, seconds=est, measured=False))
        print(f'N={n:5d} points={p:5d}: not run, ~{est:.0f} s per evaluation '
              '(extrapolated)', flush=True)
        continue
      ref = pool[:n]
      vals = {m: [] for m in METRICS}
      times = []
      for s in range(a.seeds):
        gen = pool[n * (s + 1): n * (s + 2)]
        dt, m = common.seconds(lambda: protocol.compare(ref, gen, angles, sensor=sensor,
                                                        num_points=p, seed=s))
        times.append(dt)
        for k in METRICS:
          vals[k].append(m[k])
      sec = float(np.median(times))
      measured[(n, p)] = sec
      row = dict(n=n, points=p, seconds=sec, measured=True,
                 **{f'{k}_mean': float(np.mean(v)) for k, v in vals.items()},
                 **{f'{k}_std': float(np.std(v)) for k, v in vals.items()})
      rows.append(row)
      print(f'N={n:5d} points={p:5d}: {sec:7.1f} s  ' + '  '.join(
          f'{k} {row[k + "_mean"]:.4g}+-{row[k + "_std"]:.2g}' for k in METRICS),
          flush=True)
  done = [r for r in rows if r['measured']]
  full = max(done, key=lambda r: (r['n'], r['points']))
  ok = [r for r in done if all(
      abs(r[f'{k}_mean'] - full[f'{k}_mean']) <= 2 * max(full[f'{k}_std'], r[f'{k}_std'], 1e-12)
      for k in METRICS if k != 'mmd' or r['points'] == full['points'])]
  cheapest = min(ok, key=lambda r: r['seconds'])
  print(f'largest measured: N={full["n"]}, {full["points"]} points; cheapest within '
        f'its spread: N={cheapest["n"]}, {cheapest["points"]} points '
        f'({cheapest["seconds"]:.1f} s vs {full["seconds"]:.1f} s). MMD scales with '
        'the point count (denser clouds, smaller distances), so it is compared only '
        'at equal points.')
  common.write_json(os.path.join(a.out, 'eval_tradeoff.json'), dict(
      rows=rows, seeds=a.seeds, cheapest=cheapest, full=full,
      device=info['device_kind'], cpus=info['cpus']))
  series = {}
  for p in points:
    rs = [r for r in rows if r['points'] == p and r['seconds']]
    series[f'{p} points (s per evaluation)'] = ([r['n'] for r in rs],
                                                [r['seconds'] for r in rs])
  writers.line_plot(os.path.join(a.out, 'eval_tradeoff_time.png'), series,
                    'N clouds per set (log)', 'seconds', logx=True,
                    title='unmeasured points extrapolated')
  series = {}
  for p in points:
    rs = [r for r in rows if r['points'] == p and r['measured']]
    series[f'1-NNA, {p} points'] = ([r['n'] for r in rs], [r['1nna_mean'] for r in rs])
    series[f'COV, {p} points'] = ([r['n'] for r in rs], [r['cov_mean'] for r in rs])
  writers.line_plot(os.path.join(a.out, 'eval_tradeoff_values.png'), series,
                    'N clouds per set (log)', 'value', logx=True,
                    title=f'mean of {a.seeds} seeds')


if __name__ == '__main__':
  main()
