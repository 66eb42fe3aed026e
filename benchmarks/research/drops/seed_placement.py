"""Drop placement over training seeds and at the paper's width (issue 37).

Draws, from calibrated_models.py's record of several training seeds (models
named NAME (as shipped) and NAME (levels)), each seed's AUC on surfaces < 40 m
and within rings as trained and with levels per (ring, depth) cell, beside
the per-ring table; and, from a training run's metrics.jsonl, the drop rate
of the generated batch over training. Prints the mean and spread per form.

    python benchmarks/research/drops/seed_placement.py --seeds results/seeds_test.json \
        --metrics RUN/metrics.jsonl --out results/seed_placement.png
"""

from __future__ import annotations

import argparse
import json

import numpy as np

KEYS = (('auc_near', 'AUC, surfaces < 40 m'), ('auc_near_within_ring', 'within-ring AUC, < 40 m'))


def forms(record: dict) -> dict:
  """form -> {metric: [value per seed]} of a calibrated_models record."""
  out = {}
  for name, r in sorted(record['models'].items()):
    form = name[name.index('(') + 1:-1].replace('as shipped', 'as trained')
    row = out.setdefault(form, {})
    for key, _ in KEYS:
      row.setdefault(key, []).append(r['placement'][key])
    row.setdefault('ece', []).append(r['placement']['ece'])
    row.setdefault('drop', []).append(r['sample_drop_rate'])
    for key in ('jsd', 'mmd', 'cov', '1nna'):
      row.setdefault(key, []).append(r['synthesis'][key])
  return out


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  p.add_argument('--seeds', required=True,
                 help="calibrated_models.py's JSON over seeds (several, comma-separated: "
                      'their forms side by side, of one split)')
  p.add_argument('--metrics', default='', help="a run's metrics.jsonl (drop rate panel)")
  p.add_argument('--label', default='paper width, faithful (H200)')
  p.add_argument('--out', required=True, help='the PNG to write')
  a = p.parse_args(argv)
  records = []
  for path in a.seeds.split(','):
    with open(path) as f:
      records.append(json.load(f))
  if len({r['split'] for r in records}) > 1:
    raise SystemExit(f'--seeds: records of several splits ({a.seeds})')
  record = {**records[0], 'models': {k: v for r in records for k, v in r['models'].items()}}
  by_form = forms(record)
  for form, row in by_form.items():
    print(form + ': ' + ', '.join(f'{k} {np.mean(v):.3f} +- {np.std(v, ddof=1):.3f}'
                                  for k, v in row.items()))
  import matplotlib
  matplotlib.use('Agg')
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(1, 3 if a.metrics else 2, figsize=(13 if a.metrics else 9, 3.8))
  for ax, (key, what) in zip(axes, KEYS):
    for i, (form, row) in enumerate(by_form.items()):
      v = row[key]
      ax.plot(np.full(len(v), i) + np.linspace(-0.1, 0.1, len(v)), v, 'o', ms=5, label=form)
    ax.axhline(record['ring_table'][key], color='k', lw=0.8, ls='--', label='per-ring table')
    ax.set(xticks=range(len(by_form)), xticklabels=list(by_form), ylabel=what,
           title=f'{len(v)} training seeds, {record["split"]} split')
    ax.legend(fontsize=7)
  if a.metrics:
    rows = [json.loads(line) for line in open(a.metrics)]
    rows = [r for r in rows if 'drop_rate' in r]
    axes[2].plot([r['step'] for r in rows], [r['drop_rate'] for r in rows], label='generated')
    axes[2].plot([r['step'] for r in rows], [r['real_drop_rate'] for r in rows], 'k--', lw=0.8,
                 label='real')
    axes[2].set(xlabel='step', ylabel='drop rate of the batch', yscale='log', title=a.label)
    axes[2].legend(fontsize=7)
  fig.tight_layout()
  fig.savefig(a.out, dpi=110)
  print(f'wrote {a.out}')


if __name__ == '__main__':
  main()
