"""Does an XLA CPU flag make the training step faster? A sweep, in one run.

    python benchmarks/research/speed/xla_flags.py [--scales study] [--impls matmul,xla]
        [--rounds 3] [--sets default,xnnpack,...]

Each flag set (SETS below) runs ``benchmarks/train_step.py`` in its own
process with that XLA_FLAGS (flags are read once, when the backend starts),
round-robin for ``--rounds`` rounds so that the machine's drift falls on
every set alike. Prints the median seconds per step (R1 every step) of each
set and its ratio to ``default`` measured in the same run, and writes
benchmarks/research/speed/results/xla_flags.json. A flag this jaxlib does not know makes
its process fail: that set is reported as failed, not skipped silently.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

# benchmarks/ holds common.py, shared with the product benchmarks.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..'))
import common

HERE = os.path.dirname(os.path.abspath(__file__))
BENCHMARKS = os.path.join(HERE, '..', '..')  # train_step.py

SETS = {
    'default': '',
    'xnnpack': '--xla_cpu_use_xnnpack=true',
    'xnn_fusion_dot': '--xla_cpu_experimental_xnn_fusion_type=dot',
    'xnn_graph_fusion': '--xla_cpu_experimental_xnn_graph_fusion_mode=XNN_GRAPH_FUSION_MODE_GREEDY',
    'onednn': '--xla_cpu_use_onednn=true',
    'onednn_fusion_dot': '--xla_cpu_experimental_onednn_fusion_type=dot',
    'ynn_fusion_dot': '--xla_cpu_experimental_ynn_fusion_type=dot',
    'concurrency_scheduler': '--xla_cpu_enable_concurrency_optimized_scheduler=true',
    'vector_512': '--xla_cpu_prefer_vector_width=512',
    'concurrency_vector_512': ('--xla_cpu_enable_concurrency_optimized_scheduler=true '
                               '--xla_cpu_prefer_vector_width=512'),
    'onednn_concurrency': ('--xla_cpu_use_onednn=true '
                           '--xla_cpu_enable_concurrency_optimized_scheduler=true'),
    # CPU devices for the data-parallel step ('default': the library's
    # choice, parallel.use_cpu_cores: up to two per core, shards of 4 or more).
    'one_device': '--xla_force_host_platform_device_count=1',
    'two_devices': '--xla_force_host_platform_device_count=2',
    'four_devices': '--xla_force_host_platform_device_count=4',
    'eight_devices': '--xla_force_host_platform_device_count=8',
}


def run_once(flags: str, scales: str, impls: str, repeats: int) -> dict:
  with tempfile.TemporaryDirectory() as tmp:
    out = os.path.join(tmp, 'step.json')
    env = dict(os.environ, XLA_FLAGS=flags)
    env.pop('JAX_COMPILATION_CACHE_DIR', None)  # a cached program ignores the flags.
    p = subprocess.run([sys.executable, os.path.join(BENCHMARKS, 'train_step.py'),
                        '--scales', scales, '--impls', impls, '--repeats', str(repeats),
                        '--out', out],
                       env=env, capture_output=True, text=True)
    if p.returncode:
      return {'error': (p.stderr.strip().splitlines() or ['?'])[-1]}
    with open(out) as f:
      return json.load(f)


def step_seconds(rec: dict) -> dict:
  """{(scale, impl): seconds per step with R1} of one train_step.py record."""
  out = {}
  for r in rec.get('rows', []):
    if r['r1']:
      out[f"{r['scale']}/{r['impl']}"] = r['median_s']
  return out


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--sets', default=','.join(SETS))
  p.add_argument('--scales', default='study')
  p.add_argument('--impls', default='matmul,xla')
  p.add_argument('--rounds', type=int, default=3)
  p.add_argument('--repeats', type=int, default=5)
  p.add_argument('--out', default=os.path.join(HERE, 'results', 'xla_flags.json'))
  a = p.parse_args(argv)
  names = [s for s in a.sets.split(',') if s]
  for s in names:
    if s not in SETS:
      sys.exit(f'error: unknown flag set {s!r}; known: {", ".join(SETS)}')
  common.print_banner()
  times = {s: {} for s in names}
  errors = {}
  for r in range(a.rounds):
    for s in names:
      if s in errors:
        continue
      rec = run_once(SETS[s], a.scales, a.impls, a.repeats)
      if 'error' in rec:
        errors[s] = rec['error']
        print(f'round {r + 1} {s:24s} failed: {rec["error"]}', flush=True)
        continue
      for k, v in step_seconds(rec).items():
        times[s].setdefault(k, []).append(v)
      print(f'round {r + 1} {s:24s} ' + '  '.join(
          f'{k} {v:.3f} s' for k, v in step_seconds(rec).items()), flush=True)
  base = {k: float(np.median(v)) for k, v in times.get('default', {}).items()}
  print('\nmedian seconds per step (R1 every step), ratio to default in this run:')
  summary = {}
  for s in names:
    if s in errors:
      summary[s] = {'flags': SETS[s], 'error': errors[s]}
      continue
    med = {k: float(np.median(v)) for k, v in times[s].items()}
    # Each round's ratio to that round's default: the machine's drift
    # between rounds cancels.
    paired = {k: float(np.median(np.divide(v, times['default'][k][:len(v)])))
              for k, v in times[s].items() if k in base and len(times['default'][k]) >= len(v)}
    summary[s] = {'flags': SETS[s], 'median_s': med, 'runs_s': times[s],
                  'ratio_to_default': {k: v / base[k] for k, v in med.items() if k in base},
                  'median_round_ratio': paired}
    print(f'  {s:24s} ' + '  '.join(
        f'{k} {v:.3f} s (x{v / base[k]:.2f}; per round x{paired.get(k, float("nan")):.2f})'
        if k in base else f'{k} {v:.3f} s' for k, v in med.items()))
  common.write_json(a.out, dict(rounds=a.rounds, repeats=a.repeats, sets=summary))


if __name__ == '__main__':
  main()
