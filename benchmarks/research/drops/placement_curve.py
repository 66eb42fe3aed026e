"""Drop placement over training (issue 37): at every kept checkpoint of one
or more training runs, held-out simulated scans are inverted by the EMA
generator and its measurability is scored against the simulator's truth
(evaluation.restoration's ``placement``: AUC on surfaces nearer than 40 m,
the AUC within rings there, ECE), as trained and with its level calibrated
per ring after training (:func:`calibrate_rings`), beside the training
split's per-ring table. The drop rate of the training log comes along.

    python benchmarks/research/drops/placement_curve.py \
        --runs faithful=RUN_A,other=RUN_B --split val --num 64 --steps 300

Forms: as trained, one offset per ring, and levels per (ring, depth) cell
(dusty_jax.levels), each with the drop rate of 256 samples. ``--follow STEP``
scores a run while it trains. Writes NAME.json (after every checkpoint) and
NAME.png to --out. Choose on --split val; report test.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, '..', '..'))  # benchmarks/common.py

import common  # noqa: E402

CALIBRATION_SAMPLES = 256


def calibrate_rings(params, ring_keep, num: int = CALIBRATION_SAMPLES, seed: int = 3):
  """``params`` with one measurability offset per ring (the model's
  ring_bias, added if absent) moved so that, over ``num`` samples, each
  ring's mean measurability equals ``ring_keep`` (H,): the level per ring
  fitted after training, the ranking within rings the generator's own."""
  import jax
  import jax.numpy as jnp
  variant, module = params.variant, params.module()
  key, raw = jax.random.key(seed), []
  for i in range(0, num, 64):
    z = jax.random.normal(jax.random.fold_in(key, i), (min(64, num - i), params.latent_dim))
    raw.append(np.asarray(module.apply(params.variables, z)))
  logit = np.asarray(variant.logit(jnp.asarray(np.concatenate(raw))), np.float64)
  pixel = logit[..., 0] if logit.ndim == 4 else logit
  def keep(offset):
    moved = pixel + offset[None, :, None]
    moved = np.stack([moved, logit[..., 1]], -1) if logit.ndim == 4 else moved
    return np.asarray(variant.probability(jnp.asarray(moved)), np.float64).mean(axis=(0, 2))
  lo, hi = np.full(pixel.shape[1], -60.0), np.full(pixel.shape[1], 60.0)
  target = np.clip(np.asarray(ring_keep, np.float64), 1e-4, 1 - 1e-4)
  for _ in range(50):  # bisection per ring: the mean keep rises with the offset
    mid = (lo + hi) / 2
    low = keep(mid) < target
    lo, hi = np.where(low, mid, lo), np.where(low, hi, mid)
  p = dict(params.variables['params'])
  p['ring_bias'] = jnp.asarray((lo + hi) / 2 + np.asarray(p.get('ring_bias', 0.0)), jnp.float32)
  settings = dataclasses.replace(params.settings, ring_bias=True)
  return params.replace(variables={**params.variables, 'params': p}, settings=settings)


def training_log(workdir: str) -> dict:
  steps, rate, real = [], [], []
  with open(os.path.join(workdir, 'metrics.jsonl')) as f:
    for line in f:
      try:
        m = json.loads(line)
      except json.JSONDecodeError:  # a line the training is writing now
        continue
      if 'drop_rate' in m:
        steps.append(m['step']), rate.append(m['drop_rate']), real.append(m['real_drop_rate'])
  return {'step': steps, 'drop_rate': rate, 'real_drop_rate': real}


def score(params, depth, truth, ring_keep, steps: int) -> dict:
  from dusty_jax import evaluation
  rec = evaluation.restoration(params, depth, num_steps=steps, batch=len(depth),
                               truth=truth, ring_keep=ring_keep)
  gt = rec['ground_truth']
  return {'placement': gt['placement'], 'ring_table': gt['ring_table'],
          'completion_abs_rel': gt['complete_depth'].get('abs_rel')}


FORMS = ('trained', 'calibrated', 'levels')


def forms_of(params, train_depth, ring_keep, forms):
  """Each form of a checkpoint's generator: as trained, its level
  calibrated with one offset per ring (:func:`calibrate_rings`), and with
  drop levels per (ring, depth) cell (dusty_jax.evaluation.fit_levels; the
  records before 2026-11-27 used the fit to samples it replaced)."""
  from dusty_jax import evaluation
  make = {'trained': lambda: params,
          'calibrated': lambda: calibrate_rings(params, ring_keep),
          'levels': lambda: evaluation.fit_levels(params, train_depth)}
  for form in forms:
    yield form, make[form]()


def sample_drop_rate(params, num: int = 256) -> float:
  import jax
  from dusty_jax import codec, sampling
  scans = np.asarray(sampling.sample_scans(params, jax.random.key(11), num))
  return float(np.mean(scans <= codec.ALPHA))


def run_curve(workdir: str, depth, truth, ring_keep, steps: int, every: int, log,
              at=(), forms=FORMS, train_depth=None, follow: int = 0, deadline: float = 0.0,
              save=lambda out: None) -> dict:
  """Scores each kept checkpoint of ``workdir`` in each of ``forms``. With
  ``follow`` > 0, waits for checkpoints of a run still training until one
  at or past step ``follow`` is listed, or time.time() passes ``deadline``; ``save(out)``
  is called after each checkpoint, so a cut-off run keeps what it scored."""
  import time
  from dusty_jax import checkpoint, generator
  out = {'step': [], **{f: [] for f in forms}}
  done = set()
  while True:
    mngr = checkpoint.manager(workdir, keep=100000) if os.path.isdir(
        os.path.join(workdir, 'checkpoints')) else None
    seen = sorted(mngr.all_steps()) if mngr else []
    todo = [s for s in seen
            if s and s not in done and not (every and s % every) and not (at and s not in at)]
    for s in todo:
      done.add(s)
      params, _ = generator.load(workdir, step=s, log=lambda *_: None)
      out['step'].append(s)
      line = [f'  step {s}:']
      for form, p in forms_of(params, train_depth, ring_keep, forms):
        r = score(p, depth, truth, ring_keep, steps)
        r['sample_drop_rate'] = sample_drop_rate(p)
        out[form].append(r)
        t = r['placement']
        line.append(f'{form} AUC<40 {t["auc_near"]:.3f} within {t["auc_near_within_ring"]:.3f} '
                    f'ECE {t["ece"]:.3f} drop {r["sample_drop_rate"]:.3f} |')
      out['log'] = training_log(workdir)
      save(out)
      log(' '.join(line))
    if not follow or (seen and max(seen) >= follow) or (deadline and time.time() > deadline):
      break
    time.sleep(5)
  out['log'] = training_log(workdir) if os.path.exists(
      os.path.join(workdir, 'metrics.jsonl')) else {'step': [], 'drop_rate': [], 'real_drop_rate': []}
  return out


def plot(results: dict, table: dict, path: str, title: str):
  import matplotlib
  matplotlib.use('Agg')
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
  for (name, r), color in zip(results.items(), plt.cm.tab10.colors):
    for kind, style in (('trained', '-'), ('calibrated', ':'), ('levels', '--')):
      for ax, key in zip(axes[:2], ('auc_near', 'auc_near_within_ring')):
        if r.get(kind):
          ax.plot(r['step'], [x['placement'][key] for x in r[kind]], style, color=color,
                  marker='o', ms=3, label=f'{name} ({kind})')
    axes[2].plot(r['log']['step'], r['log']['drop_rate'], color=color, label=name)
  for ax, key, what in zip(axes[:2], ('auc_near', 'auc_near_within_ring'),
                           ('AUC, surfaces < 40 m', 'within-ring AUC, < 40 m')):
    ax.axhline(table[key], color='k', lw=0.8, ls='--', label='per-ring table')
    ax.set(xlabel='step', ylabel=what)
  first = next(iter(results.values()))['log']
  axes[2].plot(first['step'], first['real_drop_rate'], 'k--', lw=0.8, label='real')
  axes[2].set(xlabel='step', ylabel='drop rate of the generated batch', yscale='log')
  for ax in axes:
    ax.legend(fontsize=7)
  fig.suptitle(title, fontsize=10)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--runs', default='', help='NAME=WORKDIR,... (training run directories)')
  p.add_argument('--data-dir', help='the prepared simulated dataset the runs used')
  p.add_argument('--split', default='val', choices=('val', 'test'))
  p.add_argument('--num', type=int, default=64, help='held-out scans inverted')
  p.add_argument('--steps', type=int, default=300, help='inversion iterations')
  p.add_argument('--every', type=int, default=0, help='only checkpoints at multiples of this')
  p.add_argument('--at', default='', help='only these checkpoint steps (comma-separated)')
  p.add_argument('--forms', default=','.join(FORMS), help=f'of {", ".join(FORMS)}')
  p.add_argument('--follow', type=int, default=0,
                 help='wait for a run still training until this step is scored')
  p.add_argument('--minutes', type=float, default=0,
                 help='with --follow: stop waiting after this (0: wait until the step)')
  p.add_argument('--out', default=os.path.join(HERE, 'results'))
  p.add_argument('--name', default='placement_curve')
  p.add_argument('--title', default='drop placement over training')
  p.add_argument('--plot-only', action='store_true', help='redraw NAME.png from NAME.json')
  a = p.parse_args(argv)
  path = os.path.join(a.out, f'{a.name}.json')
  if a.plot_only:
    with open(path) as f:
      record = json.load(f)
    plot(record['runs'], record['ring_table'], path[:-5] + '.png', a.title)
    return
  if not a.runs or not a.data_dir:
    p.error('--runs and --data-dir are needed (or --plot-only)')
  import time
  from dusty_jax import evaluation
  from dusty_jax.data import arrays
  from dusty_jax.metrics import ground_truth
  from dusty_jax.sensor import get_sensor
  with open(os.path.join(a.data_dir, 'meta.json')) as f:
    sensor = get_sensor(json.load(f)['sensor'])
  depth, complete, prob = (np.asarray(arrays.load_split(a.data_dir, a.split, sensor, k)[:a.num])
                           for k in ('', 'complete', 'drop_prob'))
  train = np.asarray(arrays.load_split(a.data_dir, 'train', sensor)[:evaluation.RING_TABLE_SCANS])
  ring_keep = evaluation.training_ring_keep(a.data_dir, sensor)
  table = ground_truth.ring_table_scores(sensor, ring_keep, depth, complete, prob)
  table.pop('reliability')
  os.makedirs(a.out, exist_ok=True)
  record = {'machine': common.machine(), 'split': a.split, 'num': a.num, 'steps': a.steps,
            'ring_table': table, 'runs': {}}

  def save(name, out):
    record['runs'][name] = out
    with open(path + '.tmp', 'w') as f:
      json.dump(record, f, indent=1)
    os.replace(path + '.tmp', path)

  deadline = time.time() + 60 * a.minutes if a.minutes else 0.0
  forms = tuple(f for f in a.forms.split(',') if f)
  for item in [r for r in a.runs.split(',') if r]:
    name, workdir = item.split('=', 1)
    print(f'{name} ({workdir}):', flush=True)
    at = tuple(int(s) for s in a.at.split(',') if s)
    save(name, run_curve(workdir, depth, (complete, prob), ring_keep, a.steps, a.every,
                         lambda s: print(s, flush=True), at, forms, train, a.follow, deadline,
                         lambda out, name=name: save(name, out)))
  plot(record['runs'], table, path[:-5] + '.png', a.title)
  print(f'per-ring table: AUC<40 {table["auc_near"]:.3f} within '
        f'{table["auc_near_within_ring"]:.3f}; wrote {path} and .png')


if __name__ == '__main__':
  main()
