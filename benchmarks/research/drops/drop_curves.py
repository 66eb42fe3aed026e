"""The drop rate and D's logits over training of the study-length CPU runs.

    python benchmarks/research/drops/drop_curves.py
        [--out benchmarks/research/drops/results/drops_full_length.png]

Reads the training logs committed beside each study report
(``benchmarks/research/drops/results/**/*_metrics.jsonl``: a run's ``metrics.jsonl``, copied
as ``MODEL_cpu_metrics.jsonl``; ``authors_code_metrics.jsonl`` is the authors'
PyTorch code run by ``authors_step.py --train-steps``) and plots every one of
them against the real scans' drop rate.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys

# benchmarks/ holds common.py, shared with the product benchmarks.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..'))
import common

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, 'results')
SUFFIX = '_metrics.jsonl'
LABELS = {'authors_code': "the authors' PyTorch code, their defaults"}


def load_runs(results: str = RESULTS) -> dict:
  """{run name: {key: [values by step]}} of every training log under ``results``."""
  runs = {}
  for path in sorted(glob.glob(os.path.join(results, '**', '*' + SUFFIX), recursive=True)):
    name = os.path.basename(path)[:-len(SUFFIX)].removesuffix('_cpu')
    with open(path) as f:
      recs = [json.loads(line) for line in f if line.strip()]
    recs = [r for r in recs if 'drop_rate' in r]
    runs[name] = {k: [r.get(k) for r in recs]
                  for k in ('step', 'drop_rate', 'real_drop_rate', 'd_real', 'd_fake')}
  return runs


def plot(runs: dict, out: str):
  plt = common.pyplot()
  fig, (ax_rate, ax_logit) = plt.subplots(1, 2, figsize=(13, 6.4))
  real = []
  for i, (name, r) in enumerate(runs.items()):
    colour = plt.cm.tab20(i % 20)  # more runs than the default cycle's 10 colours
    style = dict(color=colour, linewidth=1.2, alpha=0.85)
    label = LABELS.get(name, name)
    ax_rate.plot(r['step'], r['drop_rate'], label=label, **style)
    ax_logit.plot(r['step'], r['d_real'], **style)
    ax_logit.plot(r['step'], r['d_fake'], linestyle='--', **style)
    real += [v for v in r['real_drop_rate'] if v is not None]
  ax_rate.axhline(sum(real) / len(real), color='k', linestyle=':', label='real scans')
  ax_rate.set(yscale='log', xlabel='training step (batch 16)',
              ylabel='drop rate of generated scans (G, training batch)')
  # Below both panels, in columns: there are too many runs to fit inside one.
  handles, labels = ax_rate.get_legend_handles_labels()
  fig.legend(handles, labels, loc='lower center', ncol=4, fontsize=7, frameon=False)
  ax_logit.set(xlabel='training step (batch 16)', ylabel='D logits: real (solid), fake (dashed)')
  fig.suptitle('Study-length CPU runs (latent 128, channels 16..128): drop rate over training')
  fig.tight_layout(rect=(0, 0.2, 1, 1))
  fig.savefig(out, dpi=110)
  print(f'wrote {out}')


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--results', default=RESULTS)
  p.add_argument('--out', default=os.path.join(RESULTS, 'drops_full_length.png'))
  a = p.parse_args(argv)
  runs = load_runs(a.results)
  if not runs:
    raise SystemExit(f'{a.results}: no **/*{SUFFIX} training logs to plot')
  for name, r in runs.items():
    after = [v for s, v in zip(r['step'], r['drop_rate']) if s > 500]
    print(f'{name:24s} steps {r["step"][-1]:5d}  drop rate end {r["drop_rate"][-1]:.4f}'
          + (f', min after step 500 {min(after):.4f}' if after else ''))
  plot(runs, a.out)


if __name__ == '__main__':
  main()
