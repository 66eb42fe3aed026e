"""Table II across training seeds: is a variant's synthesis no worse than another's?

    python benchmarks/research/drops/training_seeds.py --groups 'NAME=RUN,RUN,...;NAME=RUN,...'
        [--split test|val] [--num 200] [--points 512] [--seeds 3]
        [--out benchmarks/research/drops/results --name training_seeds]

One training run per seed in each group (the first group is the reference).
Each run's EMA generator is scored by the library's evaluation.synthesis, the
function the evaluate command and the study call, with the same N, points and
sampling seeds for every run. Prints each run's Table II row (mean over the
sampling seeds), then per group the mean and standard deviation over its
training seeds, and per metric whether each group's mean is no worse than the
reference's and by how many standard errors of the difference. The sampling
seeds' spread inside one run is far smaller than the spread between training
seeds (the faithful DUSty-I's COV: 13.8%, 16.2% and 16.3% at three seeds), so
one run per model answers "no worse?" for that seed only.

Scores are cached in the result JSON (by run, split, N, points and seeds): a
rerun only scores what is new. A run's own evaluation.json (or
evaluation_val.json), written by ``python -m dusty_jax.tools.evaluate`` with
the same protocol, N, points and seeds, is read instead of scoring again.
Writes ``NAME.json`` and ``NAME.png`` (each metric's per-seed values and
group means).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

# benchmarks/ holds common.py, shared with the product benchmarks.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..'))
import common
from dusty_jax import configs, evaluation, generator
from dusty_jax.data import arrays, pipeline

HERE = os.path.dirname(os.path.abspath(__file__))
# Metric -> (label, scale, True if higher is better): the Table II columns.
METRICS = {'jsd': ('JSD x1e2', 1e2, False), 'cov': ('COV %', 1e2, True),
           'mmd': ('MMD x1e3', 1e3, False), '1nna': ('1-NNA %', 1e2, False),
           'swd': ('SWD', 1.0, False)}
DECIMALS = {'jsd': 2, 'cov': 2, 'mmd': 2, '1nna': 2, 'swd': 4}


def parse_groups(text: str) -> dict:
  groups = {}
  for item in [g for g in text.split(';') if g.strip()]:
    if '=' not in item:
      raise SystemExit(f'error: --groups item {item!r} is not NAME=RUN,RUN,...')
    name, runs = item.split('=', 1)
    groups[name.strip()] = [r for r in runs.split(',') if r]
  if len(groups) < 2:
    raise SystemExit('error: --groups needs a reference group and at least one other')
  return groups


def saved_record(run: str, a) -> dict | None:
  """The record the evaluate command wrote in ``run`` for this split, if it
  was made with the same protocol, N, points and sampling seeds."""
  path = os.path.join(run, 'evaluation.json' if a.split == 'test' else
                      f'evaluation_{a.split}.json')
  if not os.path.isfile(path):
    return None
  rec = json.load(open(path))
  same = (rec.get('protocol') == 'reference' and rec.get('num') == a.num and
          rec.get('points') == a.points and rec.get('split', 'test') == a.split and
          len(rec.get('seeds', {}).get('generator', ())) == a.seeds)
  return rec if same else None


def score(run: str, a) -> dict:
  """{metric: mean over the sampling seeds} of ``run``'s Table II row (the
  evaluate command's record in the run where it matches, else computed)."""
  config = configs.load(run)
  rec = saved_record(run, a)
  if rec is None:  # only then is the generator needed
    params = generator.load(run, log=lambda *_: None)[0]
    d = pipeline.dataset_dir(config, params.sensor, log=lambda *_: None)
    rec = evaluation.synthesis(params, arrays.load_split(d, a.split, params.sensor),
                               num=a.num, points=a.points, seeds=a.seeds, progress=True)
  row = next(v for k, v in rec['rows'].items() if k != evaluation.TRAINING_ROW)
  return {'seed': int(config.seed), 'per_sampling_seed': row,
          **{m: float(np.mean(row[m])) for m in METRICS}}


def summary(groups: dict, scores: dict) -> dict:
  """Per group: mean and std over its training seeds; per metric against the
  first group: no worse?, and the difference in standard errors."""
  out = {}
  for name, runs in groups.items():
    vals = {m: np.array([scores[r][m] for r in runs]) for m in METRICS}
    out[name] = {m: {'mean': float(v.mean()), 'std': float(v.std(ddof=1)) if len(v) > 1 else 0.0,
                     'n': len(v)} for m, v in vals.items()}
  ref = next(iter(groups))
  for name in list(groups)[1:]:
    for m, (_, _, higher) in METRICS.items():
      g, r = out[name][m], out[ref][m]
      se = np.sqrt(g['std'] ** 2 / g['n'] + r['std'] ** 2 / r['n'])
      better = g['mean'] - r['mean'] if higher else r['mean'] - g['mean']
      g['no_worse'] = bool(better >= 0)
      g['gain_in_se'] = float(better / se) if se > 0 else None
  return out


def picture(groups: dict, scores: dict, stats: dict, path: str):
  plt = common.pyplot()
  fig, axes = plt.subplots(1, len(METRICS), figsize=(3.2 * len(METRICS), 3.6))
  for ax, (m, (label, scale, higher)) in zip(axes, METRICS.items()):
    for i, (name, runs) in enumerate(groups.items()):
      ys = [scores[r][m] * scale for r in runs]
      ax.scatter(np.full(len(ys), i) + np.linspace(-0.12, 0.12, len(ys)), ys, s=18,
                 color=f'C{i}', zorder=3)
      mu, sd = stats[name][m]['mean'] * scale, stats[name][m]['std'] * scale
      ax.errorbar(i + 0.28, mu, yerr=sd, fmt='_', ms=14, color=f'C{i}', capsize=4)
    ax.set_xticks(range(len(groups)), list(groups), rotation=20, ha='right', fontsize=7)
    ax.set_title(f'{label} ({"higher" if higher else "lower"} is better)', fontsize=9)
    ax.grid(alpha=0.3)
  fig.suptitle('Table II per training seed (dots) and mean +- std over seeds', fontsize=10)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--groups', required=True, help="'NAME=RUN,RUN,...;NAME=RUN,...'")
  p.add_argument('--split', default='test', choices=('test', 'val'))
  p.add_argument('--num', type=int, default=200)
  p.add_argument('--points', type=int, default=512)
  p.add_argument('--seeds', type=int, default=3, help='sampling seeds per run')
  p.add_argument('--out', default=os.path.join(HERE, 'results'))
  p.add_argument('--name', default='training_seeds')
  a = p.parse_args(argv)
  groups = parse_groups(a.groups)
  for runs in groups.values():
    for r in runs:
      if not os.path.isfile(os.path.join(r, 'config.json')):
        raise SystemExit(f'error: {r}: not a training run directory (no config.json)')
  common.print_banner()
  path = os.path.join(a.out, f'{a.name}.json')
  cached = json.load(open(path)).get('scores', {}) if os.path.exists(path) else {}
  key = lambda r: f'{os.path.abspath(r)}|{a.split}|{a.num}|{a.points}|{a.seeds}'
  scores = {}
  for runs in groups.values():
    for r in runs:
      scores[r] = cached.get(key(r)) or score(r, a)
      cached[key(r)] = scores[r]
  stats = summary(groups, scores)
  cols = ''.join(f'{label:>16s}' for label, _, _ in METRICS.values())
  print(f'\n{a.split} split, N = {a.num}, {a.points} points, {a.seeds} sampling seeds per run')
  print(f'{"run":44s}{"seed":>5s}{cols}')
  for name, runs in groups.items():
    for r in runs:
      print(f'{name[:30] + " " + os.path.basename(r.rstrip("/")):44s}{scores[r]["seed"]:5d}' +
            ''.join(f'{scores[r][m] * s:16.{DECIMALS[m]}f}' for m, (_, s, _) in METRICS.items()))
  print(f'\n{"mean +- std over training seeds":49s}' +
        ''.join(f'{label:>18s}' for label, _, _ in METRICS.values()))
  for name in groups:
    print(f'{name[:49]:49s}' + ''.join(
        f'{stats[name][m]["mean"] * s:.{DECIMALS[m]}f} +- '
        f'{stats[name][m]["std"] * s:.{DECIMALS[m]}f}'.rjust(18)
        for m, (_, s, _) in METRICS.items()))
  ref = next(iter(groups))
  for name in list(groups)[1:]:
    verdict = ', '.join(
        f'{label} {"no worse" if stats[name][m]["no_worse"] else "worse"}' +
        ('' if stats[name][m]['gain_in_se'] is None else
         f' ({stats[name][m]["gain_in_se"]:+.1f} se)') for m, (label, _, _) in METRICS.items())
    print(f'{name} against {ref}: {verdict}')
  os.makedirs(a.out, exist_ok=True)
  picture(groups, scores, stats, os.path.join(a.out, f'{a.name}.png'))
  common.write_json(path, dict(split=a.split, num=a.num, points=a.points, seeds=a.seeds,
                               groups=groups, stats=stats, scores=cached))
  print(f'saved {path} and {a.name}.png')


if __name__ == '__main__':
  main()
