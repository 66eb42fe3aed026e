"""The level fitted per (ring, neighbours' depth) cell after training.

placement_curve.calibrate_rings fits one measurability offset per ring to a
trained generator; this screen fits one per (ring, depth bin) cell instead,
the cells dusty_jax.levels forms (the bin from the mean depth of a
pixel's neighbours, itself left out), on the generated complete depth
x_tilde. The offsets are set so that, over ``--samples`` generated scans,
each cell's expected keep rate equals the training split's keep rate of that
cell. The GAN's logit still ranks the pixels within a cell.

Scored on ``--num`` held-out scans inverted ``--steps`` iterations (the
inverted x_tilde gives the cells), beside the model-free tables: per ring,
and per (ring, depth) cell with the cells judged on the observed scan (what
research/drops/README.md calls the (ring, neighbours' depth) table) or on
the inverted x_tilde.

    python benchmarks/research/drops/cell_calibration.py \
        --models faithful1=RUN_A,sim-dusty1 --data-dir DIR --split val
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, '..', '..'))  # benchmarks/common.py

import calibrated_models  # noqa: E402
import common  # noqa: E402
import placement_curve  # noqa: E402

MIN_PIXELS = 50  # generated pixels a cell needs to get its own offset


def cells_of(x, sensor):
  """(B, H, W) cells of encoded scans x, neighbours judged on x > ALPHA
  (dusty_jax.levels.of_x_tilde, 64 scans at a time)."""
  import jax
  from dusty_jax import levels
  f = jax.jit(lambda a: levels.of_x_tilde(a, sensor))
  return np.concatenate([np.asarray(f(x[i:i + 64])) for i in range(0, len(x), 64)])


def real_rates(train, sensor):
  """(H * BINS,) the training scans' keep rate per cell, sparse cells pulled
  to their ring's rate (dusty_jax.levels.observed_keep), the cells judged
  on the observed scans."""
  from dusty_jax import codec, levels
  index = np.asarray(levels.cells(codec.encode(train, sensor),
                                  codec.valid_depth(train, sensor), sensor))
  return levels.observed_keep(index, codec.valid_depth(train, sensor), sensor.shape[0])[0].ravel()


def pixel_logit_and_gate(params, raw):
  """(pixel logit, gate): the measurability is sigmoid(logit) * gate."""
  import jax.numpy as jnp
  from dusty_jax import codec
  v = params.variant
  logit = np.asarray(v.logit(jnp.asarray(raw)), np.float64)
  x = np.tanh(np.asarray(raw[..., 0], np.float64))
  gate = (x > codec.ALPHA).astype(np.float64)
  if logit.ndim == 4:  # DUSty-II: the image-level logit switches a scan off
    gate = gate * (logit[..., 1] > 0)
    logit = logit[..., 0]
  return logit, gate, x


def fit_cells(params, rate, num: int, seed: int = 3):
  """(H * BINS,) logit offsets per cell over ``num`` samples of ``params``."""
  import jax
  module = params.module()
  apply = jax.jit(module.apply)
  key, raw = jax.random.key(seed), []
  for i in range(0, num, 64):
    z = jax.random.normal(jax.random.fold_in(key, i), (min(64, num - i), params.latent_dim))
    raw.append(np.asarray(apply(params.variables, z)))
  logit, gate, x = pixel_logit_and_gate(params, np.concatenate(raw))
  cells = cells_of(x.astype(np.float32), params.sensor).ravel()
  logit, gate = logit.ravel(), gate.ravel()
  n = len(rate)
  count = np.bincount(cells, minlength=n)
  lo, hi = np.full(n, -30.0), np.full(n, 30.0)
  target = np.clip(rate, 1e-4, 1 - 1e-4)
  for _ in range(40):
    mid = (lo + hi) / 2
    p = gate / (1 + np.exp(-(logit + mid[cells])))
    keep = np.bincount(cells, p, minlength=n) / np.maximum(count, 1)
    low = keep < target
    lo, hi = np.where(low, mid, lo), np.where(low, hi, mid)
  return np.where(count >= MIN_PIXELS, (lo + hi) / 2, 0.0)


def sample_cells(params, offsets, rate, num: int, seed: int = 11):
  """(cell-calibrated scans, scans whose keep is the cell table alone) of
  ``num`` samples: each pixel kept with its probability (the test-time
  Gumbel-sigmoid mask is a Bernoulli draw of it)."""
  import jax
  from dusty_jax import codec
  apply = jax.jit(params.module().apply)
  key, out_cal, out_table = jax.random.key(seed), [], []
  rng = np.random.default_rng(seed)
  for i in range(0, num, 64):
    z = jax.random.normal(jax.random.fold_in(key, i), (min(64, num - i), params.latent_dim))
    logit, gate, x = pixel_logit_and_gate(params, np.asarray(apply(params.variables, z)))
    cells = cells_of(x.astype(np.float32), params.sensor)
    p_cal = gate / (1 + np.exp(-(logit + offsets[cells])))
    p_table = rate[cells] * (x > codec.ALPHA)
    for p, out in ((p_cal, out_cal), (p_table, out_table)):
      out.append(np.where(rng.random(p.shape) < p, x, codec.ALPHA).astype(np.float32))
  return np.concatenate(out_cal), np.concatenate(out_table)


def table_two(params, fakes: dict, split, num: int, points: int, seeds: int = 1) -> dict:
  """Table II (mean over ``seeds``) of each of ``fakes`` against ``split``."""
  from dusty_jax import evaluation
  from dusty_jax.metrics import protocol
  ref = evaluation.encoded_subset(split, num, 'reference', params.sensor)
  cache, out = {}, {}
  for name, fake in fakes.items():
    rows = [protocol.compare(ref, fake[:len(ref)], params.angles, sensor=params.sensor,
                             protocol='reference', num_points=points, seed=s, cache=cache)
            for s in range(seeds)]
    out[name] = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
  return out


def score(params, offsets, rate, depth, truth, steps):
  """Placement scores of the cell-calibrated measurability and of the two
  cell tables, over the inverted scans."""
  from dusty_jax import codec, evaluation
  from dusty_jax.metrics import ground_truth
  sensor = params.sensor
  m_cal, m_xt, obs = [], [], []
  for _, d, _, _, res in evaluation.restore_batches(params, depth, num_steps=steps, batch=16):
    m = np.clip(np.asarray(res['measurability'], np.float64), 1e-7, 1 - 1e-7)
    cells = cells_of(np.asarray(res['inv_depth'], np.float32), sensor)
    moved = 1 / (1 + np.exp(-(np.log(m) - np.log1p(-m) + offsets[cells])))
    m_cal.append(np.where(np.asarray(res['measurability']) > 0, moved, 0.0))
    m_xt.append(rate[cells])
    obs.append(d)
  obs = np.concatenate(obs)
  comp, prob = truth
  brief = lambda s: {k: s[k] for k in evaluation.PLACEMENT}
  table_obs = rate[cells_of(np.asarray(codec.encode(obs, sensor)), sensor)]
  return {name: brief(ground_truth.measurability_scores(sensor, m, obs, comp, prob))
          for name, m in (('cell_calibrated', np.concatenate(m_cal)),
                          ('cell_table_on_x_tilde', np.concatenate(m_xt)),
                          ('cell_table_on_observed', table_obs))}


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  p.add_argument('--models', required=True, help='NAME or NAME=WORKDIR, comma-separated')
  p.add_argument('--data-dir', required=True)
  p.add_argument('--split', default='val', choices=('val', 'test'))
  p.add_argument('--num', type=int, default=64)
  p.add_argument('--steps', type=int, default=300)
  p.add_argument('--samples', type=int, default=256)
  p.add_argument('--train-scans', type=int, default=1024)
  p.add_argument('--synthesis', type=int, default=0, help='scans per Table II set (0: none)')
  p.add_argument('--points', type=int, default=512)
  p.add_argument('--out', default=os.path.join(HERE, 'results'))
  p.add_argument('--name', default='cell_calibration')
  a = p.parse_args(argv)
  from dusty_jax import evaluation
  from dusty_jax.data import arrays
  from dusty_jax.sensor import get_sensor
  with open(os.path.join(a.data_dir, 'meta.json')) as f:
    sensor = get_sensor(json.load(f)['sensor'])
  depth, complete, prob = (np.asarray(arrays.load_split(a.data_dir, a.split, sensor, k)[:a.num])
                           for k in ('', 'complete', 'drop_prob'))
  train = np.asarray(arrays.load_split(a.data_dir, 'train', sensor)[:a.train_scans])
  rate = real_rates(train, sensor)
  ring_keep = evaluation.training_ring_keep(a.data_dir, sensor)
  results = {}
  for item in [m for m in a.models.split(',') if m]:
    name, params = calibrated_models.load(item)
    ringcal = placement_curve.calibrate_rings(params, ring_keep)
    offsets = fit_cells(ringcal, rate, a.samples)
    r = score(ringcal, offsets, rate, depth, (complete, prob), a.steps) if a.num else {}
    for k, m in r.items():
      print(f'{name} {k}: AUC<40 {m["auc_near"]:.3f} within {m["auc_near_within_ring"]:.3f} '
            f'ECE {m["ece"]:.3f}', flush=True)
    if a.synthesis:
      import jax
      from dusty_jax import sampling
      split = np.asarray(arrays.load_split(a.data_dir, a.split, sensor))
      cal, table = sample_cells(ringcal, offsets, rate, a.synthesis)
      fakes = {'ring_calibrated': sampling.sample_scans(ringcal, jax.random.key(11), a.synthesis),
               'cell_calibrated': cal, 'cell_table_on_x_tilde': table}
      r['synthesis'] = table_two(params, fakes, split, a.synthesis, a.points)
      for k, m in r['synthesis'].items():
        print(f'{name} {k}: drop {np.mean(fakes[k] <= -1):.3f} JSD x1e2 {100 * m["jsd"]:.1f} '
              f'MMD x1e3 {1e3 * m["mmd"]:.2f} 1-NNA {100 * m["1nna"]:.1f} COV '
              f'{100 * m["cov"]:.1f}', flush=True)
    results[name] = r
  os.makedirs(a.out, exist_ok=True)
  with open(os.path.join(a.out, f'{a.name}.json'), 'w') as f:
    json.dump({'machine': common.machine(), 'split': a.split, 'num': a.num,
               'steps': a.steps, 'samples': a.samples, 'models': results}, f, indent=1)


if __name__ == '__main__':
  main()
