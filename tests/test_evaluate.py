"""The evaluation protocol and its CLI on a tiny run."""

import json
import os
import subprocess
import sys

import jax
import numpy as np

from dusty_jax import projection
from dusty_jax.metrics import protocol


def test_protocol_identical_sets(tiny):
  rng = np.random.default_rng(0)
  d = rng.uniform(3, 60, (6,) + tiny.shape).astype(np.float32)
  d[:, :2] = 0
  x = np.asarray(projection.encode(d, tiny))
  m, (d_rr, ref) = protocol.compare(x, x, tiny.nominal_angles(), tiny, 64,
                                    jax.random.key(0))
  assert m['cov'] == 1.0 and m['mmd'] < 1e-7 and abs(m['jsd']) < 1e-12
  assert d_rr.shape == (6, 6) and ref[0].shape == (6, 64, 3)
  far = np.asarray(projection.encode(d * 0.3, tiny))
  m2, _ = protocol.compare(x, far, tiny.nominal_angles(), tiny, 64,
                           jax.random.key(0), d_rr=d_rr, ref=ref)
  assert m2['nna'] == 1.0 and m2['jsd'] > 0.1 and m2['mmd'] > 0
  table = protocol.format_table({'a': {k: [v, v] for k, v in m2.items()}})
  assert 'JSD x1e2' in table and '+-' in table


def test_evaluate_cli(smoke_run, tmp_path):
  _, workdir, _ = smoke_run
  env = dict(os.environ)
  env.pop('XLA_FLAGS', None)
  r = subprocess.run([sys.executable, '-m', 'dusty_jax.evaluate', '--workdir', workdir,
                      '--num', '4', '--points', '32', '--seeds', '2'], env=env,
                     capture_output=True, text=True, timeout=600)
  assert r.returncode == 0, r.stderr[-3000:]
  assert 'training set' in r.stdout and 'COV %' in r.stdout
  ev = json.load(open(os.path.join(workdir, 'evaluation.json')))
  row = ev['rows']['dusty1']
  assert len(row['jsd']) == 2 and all(0 <= c <= 1 for c in row['cov'])
  assert all(0 <= v <= 1 for v in row['nna']) and all(v > 0 for v in row['mmd'])


def test_tolerance_tuning_baseline(tiny):
  """HyperOpt tunes beta for the baseline: the score at the chosen beta is
  no worse than at the ends of the search range."""
  from dusty_jax import evaluate, trainer
  from train_helpers import tiny_config
  setup = trainer.make_setup(tiny_config(model='baseline'), tiny)
  state = trainer.init_state(setup, jax.random.key(0))
  params = trainer.generator_bundle(setup, state.g_params, tiny.nominal_angles())
  rng = np.random.default_rng(1)
  d = rng.uniform(3, 60, (8,) + tiny.shape).astype(np.float32)
  d[rng.uniform(size=d.shape) < 0.2] = 0
  val = np.asarray(projection.encode(d, tiny))
  beta = evaluate.tune_tolerance(params, val, trials=6, points=32)
  assert 1e-3 <= beta <= 1e-1
  gen = evaluate._sample_scans(params, jax.random.key(0), len(val))
  score = lambda b: protocol.tolerance_score(protocol.compare(
      val, gen, params.angles, tiny, 32, jax.random.key(0), tolerance_gen=b)[0])
  assert score(beta) <= max(score(1e-3), score(1e-1)) + 1e-9
