"""Evaluates a training run with the paper's synthesis metrics (Table II).

    python -m dusty_jax.evaluate --workdir RUN [--num 5000] [--points 2048] [--seeds 5]
        [--protocol reference|paper]

Samples from the EMA generator, compares with the test split of the run's
dataset, and prints mean +- std over seeds, with the "training set" row
(train vs test) for reference. ``--protocol paper`` computes as the
authors' code does, test subset included (values to set beside the paper's
Table II; see dusty_jax/metrics/protocol.py); the default, ``reference``,
follows the published metric definitions. evaluation.json records the
protocol, N, points, seeds, the test-subset rule, the sensor and the
dusty_jax version. For the baseline model, ``--tune`` first tunes the
point-drop tolerance beta on the validation split with HyperOpt (TPE,
within [1e-3, 1e-1], at 512 points), minimising JSD x 10 - COV + MMD x 1e2 +
1-NNA as in the paper. Runs on a CPU; the full protocol (5000 clouds of 2048
points) takes hours there: see benchmarks/eval_tradeoff.py for cheaper
settings and what they cost in accuracy.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--workdir', required=True)
  p.add_argument('--num', type=int, default=5000)
  p.add_argument('--points', type=int, default=2048)
  p.add_argument('--seeds', type=int, default=5)
  p.add_argument('--tolerance', type=float, default=None,
                 help="baseline's beta (default: the run's config, else 0)")
  p.add_argument('--tune', action='store_true', help='tune beta (baseline)')
  p.add_argument('--tune-trials', type=int, default=100)
  p.add_argument('--no-train-row', action='store_true')
  p.add_argument('--protocol', choices=('reference', 'paper'), default='reference',
                 help="'reference': published definitions; 'paper': the authors' code")
  a = p.parse_args(argv)
  try:
    run(a)
  except (ValueError, FileNotFoundError, ImportError) as e:
    sys.exit(f'error: {e}')


def _sample_scans(params, key, num, batch=64):
  import jax
  from dusty_jax import sampling
  out = []
  for i in range(0, num, batch):
    n = min(batch, num - i)
    res = sampling.sample(params.replace(tolerance=0.0), jax.random.fold_in(key, i), n)
    out.append(np.asarray(res['scan']))
  return np.concatenate(out)


def tune_tolerance(params, val_scans, trials: int, points: int = 512, seed: int = 0,
                   protocol: str = 'reference'):
  """Baseline's beta by HyperOpt TPE on the paper's weighted score."""
  try:
    import hyperopt
  except ImportError:
    raise ImportError('tuning needs hyperopt: pip install "dusty_jax[tune]"') from None
  import jax
  from dusty_jax import metrics
  from dusty_jax.metrics import protocol as proto
  gen = _sample_scans(params, jax.random.key(seed), len(val_scans))
  cache = {}

  def objective(beta):
    m = metrics.compare(val_scans, gen, params.angles, sensor=params.sensor,
                        protocol=protocol, num_points=points, seed=seed,
                        tolerance=beta, cache=cache)
    return proto.tolerance_score(m)

  best = hyperopt.fmin(objective, hyperopt.hp.loguniform('beta', np.log(1e-3), np.log(1e-1)),
                       algo=hyperopt.tpe.suggest, max_evals=trials,
                       rstate=np.random.default_rng(seed), show_progressbar=True)
  return float(best['beta'])


SAMPLE_SEED = 1000  # generated set s is sampled with key(SAMPLE_SEED + s).


def run(a):
  import jax
  import tqdm
  from dusty_jax import checkpoint, codec, metrics
  from dusty_jax.data import arrays, pipeline
  from dusty_jax.metrics import protocol

  params, config = checkpoint.load_checkpoint(a.workdir)
  sensor = params.sensor
  d = pipeline.dataset_dir(config, sensor, log=print)
  test = arrays.load_split(d, 'test', sensor)
  ref = np.asarray(codec.encode(test[protocol.subset(len(test), a.num, a.protocol)],
                                     sensor))
  n = len(ref)
  if n < a.num:
    print(f'note: the test subset has {n} scans; evaluating {n} per set')
  tol = a.tolerance if a.tolerance is not None else config.get('tolerance', 0.0)
  if a.tune:
    if config.model != 'baseline':
      raise ValueError('--tune is for the baseline; DUSty needs no tolerance')
    val = arrays.load_split(d, 'val', sensor)
    val = np.asarray(codec.encode(val[protocol.subset(len(val), a.num, a.protocol)],
                                       sensor))
    tol = tune_tolerance(params, val, a.tune_trials, protocol=a.protocol)
    print(f'tuned tolerance beta = {tol:.5f}')
  rows = {}
  cache = {}
  compare = lambda fake, seed, tolerance=0.0: metrics.compare(
      ref, fake, params.angles, sensor=sensor, protocol=a.protocol,
      num_points=a.points, seed=seed, tolerance=tolerance, cache=cache, progress=True)
  results = {k: [] for k, _, _ in protocol.ROW_SCALES}
  for seed in tqdm.trange(a.seeds, desc='seeds', file=sys.stderr):
    gen = _sample_scans(params, jax.random.key(SAMPLE_SEED + seed), n)
    m = compare(gen, seed, tol)
    for k in results:
      results[k].append(m[k])
  rows[f'{config.model}' + (f' (beta={tol:.4f})' if tol else '')] = results
  if not a.no_train_row:
    train = arrays.load_split(d, 'train', sensor)
    # The authors subsample the training split by the same rule and --num.
    num_train = a.num if a.protocol == 'paper' else n
    tr = np.asarray(codec.encode(
        train[protocol.subset(len(train), num_train, a.protocol)], sensor))
    m = compare(tr[:n], 0)
    rows['training set'] = {k: [v] for k, v in m.items()}
  table = protocol.format_table(rows)
  print(f'protocol {a.protocol}: N = {n} clouds of {a.points} points, {a.seeds} seeds')
  print(table)
  out = os.path.join(a.workdir, 'evaluation.json')
  seeds = {'metric': list(range(a.seeds)),
           'generator': [SAMPLE_SEED + s for s in range(a.seeds)],
           'training_row_metric': 0}
  with open(out, 'w') as f:
    json.dump({**protocol.provenance(a.protocol, n, a.points, seeds,
                                     protocol.SUBSET_RULES[a.protocol], sensor),
               'tolerance': tol, 'rows': rows}, f, indent=2)
  print(f'saved {out}')


if __name__ == '__main__':
  main()
