"""Restoration's speed/accuracy trade, from the encoder alone to full search.

    python benchmarks/encoder_trade.py [--model sim-dusty1] [--num 32] [--out benchmarks/results]

Inverts held-out simulated HDL-64E scans (scene seed --seed, which no
shipped generator trained on) with each start and number of iterations:
the encoder alone, encoder + 10/50/100/300 iterations, random start +
100/300/1000 (the paper's). Columns: the fit error on returned points and
the completion error against the simulator's complete depth (x_tilde of the
clean scan; AbsRel, as benchmarks/study.py), the Table III restoration
errors for drop:0.9 and beams:4 (against the clean scan: Chamfer x1e4 and
AbsRel), and ms per scan at batch 1 and at batch --num. Each timing is the
median of the calls after the one that compiles. Writes
encoder_trade.{json,md}, with linear interpolation of the same corrupted
scans beside the restoration columns.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

import common

HERE = os.path.dirname(os.path.abspath(__file__))
ROWS = (('encoder', 0), ('encoder', 10), ('encoder', 50), ('encoder', 100),
        ('encoder', 300), ('random', 100), ('random', 300), ('random', 1000))
CORRUPTIONS = ('drop:0.9', 'beams:4')


def parse_args(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--model', default='sim-dusty1',
                 help='a shipped generator name, a run directory or an .npz')
  p.add_argument('--num', type=int, default=32, help='test scans (the large batch)')
  p.add_argument('--seed', type=int, default=7, help='scene seed of the test scans')
  p.add_argument('--rows', default='', help='subset, e.g. encoder:0,random:100')
  p.add_argument('--repeats', type=int, default=3, help='timed calls at batch 1')
  p.add_argument('--out', default=os.path.join(HERE, 'results'))
  return p.parse_args(argv)


def load(model: str):
  import dusty_jax
  if os.path.exists(model):
    return dusty_jax.load_checkpoint(model)[0]
  return dusty_jax.load_pretrained(model)


def measure(params, obs, comp, prob, init, steps, repeats):
  import jax
  from dusty_jax import codec, corrupt, inversion
  from dusty_jax.metrics import ground_truth, reconstruction
  sensor = params.sensor
  clean = np.asarray(codec.encode(obs, sensor))
  run = lambda x: jax.device_get(inversion.invert(params, x, num_steps=steps, init=init))
  # The first call compiles; it is a corrupted input, whose result is kept.
  row = {'init': init, 'iterations': steps}
  big = []
  for spec in CORRUPTIONS:
    target = np.asarray(corrupt.apply(spec, jax.random.key(11), clean, sensor))
    dt, res = common.seconds(lambda: run(target))
    big.append(dt)
    e = reconstruction.errors(obs, res, np.asarray(params.angles), sensor)
    row[spec] = {'cd_x1e4': float(np.nanmean(e['cd'])) * 1e4,
                 'abs_rel': float(np.nanmean(e['abs_rel']))}
  dt, res = common.seconds(lambda: run(clean))
  big.append(dt)
  g = ground_truth.disentanglement(sensor, res['inv_depth'], res['measurability'],
                                   obs, comp, prob)
  row.update(fit_abs_rel=g['fit']['abs_rel'], fit_mae_m=g['fit']['mae_m'],
             completion_abs_rel=g['completion']['abs_rel'],
             completion_mae_m=g['completion']['mae_m'],
             auc_near=g['measurability']['auc_near'],
             ms_per_scan_batch=1e3 * float(np.median(big[1:])) / len(obs),
             compile_and_run_s=big[0])
  one = common.timed(lambda: run(clean[:1]), repeats)
  row['ms_per_scan_1'] = 1e3 * one.median
  return row


def report(rows, a, machine, model_name, n):
  f = lambda v, d=4: f'{v:.{d}f}'
  lines = [
      f'# Restoration: the encoder against the search ({model_name}, {n} held-out '
      f'simulated scans, scene seed {a.seed})', '',
      f'Measured on {machine["banner"]}, by `python benchmarks/encoder_trade.py '
      f'--model {a.model} --num {a.num}`. Errors are AbsRel (lower is better); fit: '
      'x_tilde on the returned points; completion: x_tilde against the complete depth '
      'where the sensor dropped a surface; drop:0.9 and beams:4: Table III, the '
      're-rendered scan against the clean one (Chamfer x1e4, AbsRel of x_tilde on its '
      'returns). ms per scan: median of the calls after the one that compiles.', '',
      f'| start | iterations | fit | completion | AUC<40 m | drop:0.9 CD | drop:0.9 AbsRel '
      f'| beams:4 CD | beams:4 AbsRel | ms/scan, batch 1 | ms/scan, batch {n} |',
      '|---|---|---|---|---|---|---|---|---|---|---|']
  for r in rows:
    lines.append(
        f'| {r["init"]} | {r["iterations"]} | {f(r["fit_abs_rel"])} | '
        f'{f(r["completion_abs_rel"])} | {f(r["auc_near"], 3)} | '
        f'{f(r["drop:0.9"]["cd_x1e4"], 2)} | {f(r["drop:0.9"]["abs_rel"])} | '
        f'{f(r["beams:4"]["cd_x1e4"], 2)} | {f(r["beams:4"]["abs_rel"])} | '
        f'{r["ms_per_scan_1"]:.1f} | {r["ms_per_scan_batch"]:.1f} |')
  return '\n'.join(lines) + '\n'


def targets(rows, n):
  """The issue's targets on this CPU, each (statement, met)."""
  by = {(r['init'], r['iterations']): r for r in rows}
  out = []
  if ('encoder', 0) in by and ('random', 300) in by:
    e, r = by[('encoder', 0)], by[('random', 300)]
    speedup = r['ms_per_scan_batch'] / e['ms_per_scan_batch']
    out.append((f'encoder alone {e["ms_per_scan_batch"]:.1f} ms/scan at batch {n} '
                '(target <= 10)', e['ms_per_scan_batch'] <= 10))
    out.append((f'{speedup:.0f}x faster than random + 300 (target >= 50x)', speedup >= 50))
  if ('encoder', 50) in by and ('random', 300) in by:
    e, r = by[('encoder', 50)]['fit_abs_rel'], by[('random', 300)]['fit_abs_rel']
    out.append((f'encoder + 50 fit {e:.4f} vs random + 300 {r:.4f} (target <= 1.05x)',
                e <= 1.05 * r))
  if ('encoder', 300) in by and ('random', 1000) in by:
    e, r = by[('encoder', 300)]['fit_abs_rel'], by[('random', 1000)]['fit_abs_rel']
    out.append((f'encoder + 300 fit {e:.4f} vs random + 1000 {r:.4f} (target: no worse)',
                e <= r))
  return out


def linear_beside(params, obs) -> dict:
  """Linear interpolation of the same corrupted scans (the draws of
  measure()), scored as Table III scores x_tilde: AbsRel over every
  return of the clean scan (metrics.restoration's scan_abs_rel)."""
  import jax
  from dusty_jax import codec, corrupt, restoration
  from dusty_jax.metrics import restoration as fill_metrics
  sensor = params.sensor
  clean = np.asarray(codec.encode(obs, sensor))
  out = {}
  for spec in CORRUPTIONS:
    known = np.asarray(corrupt.kept(spec, jax.random.key(11), clean.shape))
    filled = restoration.restore(params, np.where(known, obs, 0.0), known, method='linear')
    s = fill_metrics.scores(filled['depth'], obs, known, params.angles, sensor)
    out[spec] = float(np.nanmean(s['scan_abs_rel']))
  return out


def main(argv=None):
  a = parse_args(argv)
  machine = common.print_banner()
  import dusty_jax
  from dusty_jax.data import synthetic
  dusty_jax.enable_compilation_cache()  # as the commands: compile_and_run_s with it on
  params = load(a.model)
  if params.encoder is None:
    sys.exit(f'{a.model} has no encoder: train one with python -m '
             'dusty_jax.tools.train_encoder --workdir RUN')
  obs, comp, prob = synthetic.simulate(a.num, params.sensor, seed=a.seed,
                                       desc='simulating test scans')
  wanted = ROWS if not a.rows else tuple(
      (s.split(':')[0], int(s.split(':')[1])) for s in a.rows.split(','))
  rows = []
  for init, steps in wanted:
    rows.append(measure(params, obs, comp, prob, init, steps, a.repeats))
    r = rows[-1]
    print(f'{init:>7} + {steps:4d}: fit {r["fit_abs_rel"]:.4f}, completion '
          f'{r["completion_abs_rel"]:.4f}, drop:0.9 CD {r["drop:0.9"]["cd_x1e4"]:.2f}, '
          f'beams:4 CD {r["beams:4"]["cd_x1e4"]:.2f}; {r["ms_per_scan_1"]:.1f} ms/scan '
          f'alone, {r["ms_per_scan_batch"]:.1f} ms/scan at batch {a.num}', flush=True)
  name = os.path.basename(a.model.rstrip('/'))
  linear = linear_beside(params, obs)
  text = report(rows, a, machine, name, a.num)
  text += ('\nBeside drop:0.9 and beams:4, linear interpolation of the same corrupted scans, '
           'scored the same way: ' + ', '.join(f'{k} AbsRel {v:.4f}' for k, v in linear.items())
           + ' (benchmarks/restore.py compares every restoration).\n')
  met = targets(rows, a.num)
  text += '\nTargets (issue 20, this CPU):\n' + ''.join(
      f'- {"met" if ok else "NOT met"}: {s}\n' for s, ok in met)
  print(text)
  os.makedirs(a.out, exist_ok=True)
  common.write_json(os.path.join(a.out, 'encoder_trade.json'),
                    {'rows': rows, 'linear_interpolation': linear, 'model': a.model,
                     'num': a.num, 'seed': a.seed,
                     'targets': [{'target': s, 'met': ok} for s, ok in met]})
  with open(os.path.join(a.out, 'encoder_trade.md'), 'w') as fh:
    fh.write(text)
  print('wrote', os.path.join(a.out, 'encoder_trade.md'))


if __name__ == '__main__':
  main()
