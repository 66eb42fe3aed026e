"""The train step's speed at two commits, measured in one run, alternating.

    python benchmarks/compare_commits.py --before REV [--after REV] [--rounds 3]
        [--impls matmul] [--repeats 5]

Checks out both commits' libraries into temporary git worktrees and runs
this checkout's benchmarks/train_step.py against each in turn (before,
after, before, after, ...), so that load on a shared machine falls on both
alike. Prints per round and the median over rounds of each commit's
seconds per step (R1 on and off) and the ratio after / before; writes
benchmarks/results/compare_commits.json.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

import common

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def git(*args) -> str:
  return subprocess.run(['git', '-C', ROOT, *args], check=True, capture_output=True,
                        text=True).stdout.strip()


def measure(tree: str, args, out: str) -> dict:
  """{(impl, variant, r1): median s} of one train_step.py run on ``tree``."""
  env = dict(os.environ, PYTHONPATH=tree)
  cmd = [sys.executable, os.path.join(HERE, 'train_step.py'), '--out', out,
         '--impls', args.impls, '--variants', args.variants, '--repeats',
         str(args.repeats), '--batch', str(args.batch), '--model', args.model]
  subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL)
  with open(out) as f:
    rows = json.load(f)['rows']
  return {f'{r["impl"]} {r["variant"]} R1={"on" if r["r1"] else "off"}': r['median_s']
          for r in rows}


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--before', required=True)
  p.add_argument('--after', default='HEAD')
  p.add_argument('--rounds', type=int, default=3)
  p.add_argument('--impls', default='matmul')
  p.add_argument('--variants', default='authors')
  p.add_argument('--model', default='dusty1')
  p.add_argument('--batch', type=int, default=32)
  p.add_argument('--repeats', type=int, default=5)
  p.add_argument('--out', default=os.path.join(HERE, 'results', 'compare_commits.json'))
  a = p.parse_args()
  common.print_banner()
  revs = {'before': git('rev-parse', '--short', a.before),
          'after': git('rev-parse', '--short', a.after)}
  print(f'before {revs["before"]} ({git("log", "-1", "--format=%s", a.before)[:60]})')
  print(f'after  {revs["after"]} ({git("log", "-1", "--format=%s", a.after)[:60]})')
  runs = {'before': [], 'after': []}
  with tempfile.TemporaryDirectory() as tmp:
    trees = {}
    for name, rev in revs.items():
      trees[name] = os.path.join(tmp, name)
      git('worktree', 'add', '--detach', trees[name], rev)
    try:
      for r in range(a.rounds):
        for name in ('before', 'after'):
          res = measure(trees[name], a, os.path.join(tmp, f'{name}_{r}.json'))
          runs[name].append(res)
          print(f'round {r + 1} {name:6s} ' + ', '.join(
              f'{k}: {v:.2f} s' for k, v in res.items()), flush=True)
    finally:
      for t in trees.values():
        git('worktree', 'remove', '--force', t)
  summary = {}
  for k in runs['before'][0]:
    b = statistics.median(x[k] for x in runs['before'])
    f = statistics.median(x[k] for x in runs['after'])
    summary[k] = dict(before_s=b, after_s=f, ratio=f / b)
    print(f'{k}: before {b:.2f} s, after {f:.2f} s per step (median of {a.rounds} '
          f'rounds); after / before = {f / b:.3f}')
  common.write_json(a.out, dict(revisions=revs, args=vars(a), runs=runs, summary=summary))


if __name__ == '__main__':
  main()
