"""The EMA ramp of the CPU-scale configs against none: what the main command
prints (its final_evaluation.json), per training seed.

    # per seed S, the main command with and without the ramp (about 14 min each):
    python -m dusty_jax.train --config experiments/synthetic.py --workdir RUNS/ramp_sS --config.seed=S
    python -m dusty_jax.train --config experiments/synthetic.py --workdir RUNS/noramp_sS \\
        --config.seed=S --config.ema_rampup=0.0
    python benchmarks/research/training/ema_rampup.py RUNS/ramp_s0 RUNS/noramp_s0 ... [--out DIR]

Writes ema_rampup.json (the figures of each run) and ema_rampup.png to --out.
"""

import argparse
import json
import os

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt

HERE = os.path.dirname(os.path.abspath(__file__))
# (label, how to read it from final_evaluation.json, scale)
FIGURES = [
    ('JSD x1e2', lambda d: d['synthesis']['jsd'], 100),
    ('MMD x1e3', lambda d: d['synthesis']['mmd'], 1e3),
    ('COV %', lambda d: d['synthesis']['cov'], 100),
    ('1-NNA %', lambda d: d['synthesis']['1nna'], 100),
    ('AUC < 40 m', lambda d: d['ground_truth']['placement']['auc_near'], 1),
    ('within rings', lambda d: d['ground_truth']['placement']['auc_near_within_ring'], 1),
    ('ECE', lambda d: d['ground_truth']['placement']['ece'], 1),
    ('restoration AbsRel', lambda d: d['restoration']['abs_rel'], 1),
    ('completion AbsRel', lambda d: d['ground_truth']['complete_depth']['abs_rel'], 1),
]


def main():
  ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  ap.add_argument('runs', nargs='+', help='run directories of the main command')
  ap.add_argument('--out', default=os.path.join(HERE, 'results'))
  a = ap.parse_args()
  rows = {}
  for run in a.runs:
    with open(os.path.join(run, 'final_evaluation.json')) as f:
      d = json.load(f)
    with open(os.path.join(run, 'config.json')) as f:
      c = json.load(f)
    name = f"{'ramp' if c['ema_rampup'] else 'no ramp'}, seed {c['seed']}"
    rows[name] = {label: get(d) * scale for label, get, scale in FIGURES}
  print('| run | ' + ' | '.join(l for l, _, _ in FIGURES) + ' |')
  print('|---' * (len(FIGURES) + 1) + '|')
  for name, r in rows.items():
    print(f'| {name} | ' + ' | '.join(f'{v:.3f}' if v < 2 else f'{v:.1f}'
                                      for v in r.values()) + ' |')
  os.makedirs(a.out, exist_ok=True)
  with open(os.path.join(a.out, 'ema_rampup.json'), 'w') as f:
    json.dump({'runs': list(a.runs), 'figures': rows}, f, indent=2)
  fig, axes = plt.subplots(1, len(FIGURES), figsize=(2.2 * len(FIGURES), 3),
                           layout='constrained')
  for ax, (label, _, _) in zip(axes, FIGURES):
    names = list(rows)
    ax.bar(range(len(names)), [rows[n][label] for n in names],
           color=['tab:blue' if n.startswith('ramp') else 'tab:orange' for n in names])
    ax.set_xticks(range(len(names)), names, rotation=60, ha='right', fontsize=7)
    ax.set_title(label, fontsize=9)
  fig.savefig(os.path.join(a.out, 'ema_rampup.png'), dpi=100)


if __name__ == '__main__':
  main()
