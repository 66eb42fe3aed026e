"""Does it learn? Baseline vs DUSty-I vs DUSty-II on simulated scenes.

    python benchmarks/study.py --workdir runs/study [--scale cpu|paper]

Trains the three models (experiments/study.py) on simulated HDL-64E scans,
one after the other, each resuming where a previous call stopped; then
evaluates them on the simulated test split, whose complete depth and true
drop probability are known, and writes the report:

  * synthesis, the paper's Table II layout (SWD, JSD, COV, MMD, 1-NNA, mean
    +- std over seeds; the training-set row; the baseline's tolerance beta
    tuned on the validation split as in the paper);
  * disentanglement: test scans inverted by each model; x_tilde against the
    complete depth where the sensor dropped a surface (completion) and where
    it returned (fit); measurability against the truth (ECE, Brier, AUC);
  * restoration, Table III layout (drop 90%, 1 beam in 4, range noise),
    against the clean scan and against the complete depth (through the
    library's evaluation.restore_batches: per-scan draws of seed 7; the
    committed results/study.md predates that rule and drew one corruption
    key(7) for the set, so a rerun moves its figures by the draws alone);
  * the speed/accuracy trade of inverting the trained DUSty-I;
  * pictures: samples, the reliability diagram, restorations, and a real
    KITTI scan (../shared/data/kitti-sample, if present) restored by DUSty-I.

Everything goes to ``--workdir`` (runs/, checkpoints, per-section JSON, so a
rerun skips what is done) and the report to ``--out`` (benchmarks/results:
study.md, study.json, study_*.png). ``--export`` writes the trained DUSty-I
and baseline generators into the package (dusty_jax/pretrained/).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

import common
from dusty_jax import files

HERE = os.path.dirname(os.path.abspath(__file__))
# Run name -> (model, drops preset) of experiments/study.py.
RUNS = {'baseline': ('baseline', 'authors'), 'dusty1': ('dusty1', 'authors'),
        'dusty2': ('dusty2', 'authors'), 'dusty1_levels': ('dusty1', 'levels'),
        'dusty1_dipdrops': ('dusty1', 'dips'), 'dusty2_dipdrops': ('dusty2', 'dips')}
MODELS = tuple(RUNS)
TRADE_RUN = 'dusty1'  # the run whose inversion time vs quality (trade) is measured
LABELS = {'baseline': 'Baseline', 'dusty1': 'DUSty-I', 'dusty2': 'DUSty-II',
          'dusty1_dipdrops': 'DUSty-I, mask detached, dips filled',
          'dusty2_dipdrops': 'DUSty-II, mask detached, dips filled',
          'dusty1_levels': 'DUSty-I, drop levels per (ring, depth) cell'}
# What --export writes each model as (dusty_jax/pretrained/NAME.npz).
# sim-dusty1 is the main command's run with its encoder
# (benchmarks/research/drops/ship_run.py), not a study run.
EXPORT_NAMES = {'dusty2_dipdrops': 'sim-dusty2',
                'dusty1': 'sim-dusty1-authors', 'baseline': 'sim-baseline'}
REUSED_SECTIONS = ('synthesis', 'restoration', 'trade')
CORRUPTIONS = ('drop:0.9', 'beams:4', 'noise:0.01')
TRADE_ITERS = (50, 100, 200, 500, 1000)
KITTI_SAMPLE = os.path.join(HERE, '..', '..', 'shared', 'data', 'kitti-sample')


def parse_args(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--workdir', default='runs/study')
  p.add_argument('--out', default=os.path.join(HERE, 'results'))
  p.add_argument('--scale', default='cpu', choices=('cpu', 'paper'))
  p.add_argument('--models', default=','.join(MODELS[:3]),
                 help=f'of {MODELS}')
  p.add_argument('--steps', type=int, default=None, help='override num_steps')
  p.add_argument('--train-only', action='store_true')
  p.add_argument('--eval-only', action='store_true')
  p.add_argument('--num-synthesis', type=int, default=200,
                 help='clouds per set for Table II (test split size caps it)')
  p.add_argument('--points', type=int, default=512)
  p.add_argument('--seeds', type=int, default=3)
  p.add_argument('--tune-trials', type=int, default=12)
  p.add_argument('--num-invert', type=int, default=64)
  p.add_argument('--num-restore', type=int, default=32)
  p.add_argument('--invert-steps', type=int, default=500)
  p.add_argument('--num-trade', type=int, default=16)
  p.add_argument('--export', action='store_true',
                 help=f'write the models into dusty_jax/pretrained/ as {EXPORT_NAMES}')
  p.add_argument('--from-pretrained', default='',
                 help='MODEL=NAME,...: evaluate a shipped generator as MODEL instead '
                      'of training it (its run directory is made from the file)')
  p.add_argument('--reuse', default='',
                 help='an earlier study.json: models given by --from-pretrained take '
                      f'its {REUSED_SECTIONS} sections (the same generators) instead '
                      'of recomputing them')
  return p.parse_args(argv)


# ----------------------------------------------------------------------------
# Training.
# ----------------------------------------------------------------------------


def model_config(model, a):
  c = common.experiment('study')['study'](*RUNS[model], a.scale)
  if a.steps:
    c.num_steps = a.steps
  return c


def seed_from_pretrained(model, name, a, reuse):
  """Makes WORKDIR/MODEL a run holding the shipped generator ``name`` (once),
  with ``reuse``'s sections for it in its evaluation cache."""
  import dusty_jax
  from dusty_jax import trainer
  workdir = os.path.join(a.workdir, model)
  if not os.path.isfile(os.path.join(workdir, 'config.json')):
    print(f'== {LABELS[model]}: the shipped {name!r}, not trained here', flush=True)
    trainer.init_run(workdir, model_config(model, a), dusty_jax.load_pretrained(name))
  if reuse and model in reuse['results']:
    cache = Cache(os.path.join(workdir, 'study_eval.json'))
    for section in REUSED_SECTIONS:
      if section in reuse['results'][model] and section not in cache.data:
        cache.get(section, lambda: reuse['results'][model][section])
    if model == TRADE_RUN and 'trade' not in cache.data and 'trade' in reuse:
      cache.get('trade', lambda: reuse['trade'])


def train(model, a):
  from dusty_jax import trainer
  workdir = os.path.join(a.workdir, model)
  print(f'== training {LABELS[model]} into {workdir}', flush=True)
  t = time.time()
  trainer.train_and_evaluate(model_config(model, a), workdir)
  return time.time() - t


# ----------------------------------------------------------------------------
# Evaluation sections, each cached in WORKDIR/MODEL/study_eval.json.
# ----------------------------------------------------------------------------


class Cache:
  def __init__(self, path):
    self.path = path
    self.data = json.load(open(path)) if os.path.isfile(path) else {}

  def get(self, name, fn):
    if name not in self.data:
      t = time.time()
      self.data[name] = fn()
      self.data['seconds'] = dict(self.data.get('seconds', {}), **{name: time.time() - t})
      with files.atomic_write(self.path) as f:
        json.dump(self.data, f, indent=1)
    return self.data[name]


def load_data(config, sensor):
  from dusty_jax.data import arrays, pipeline
  d = pipeline.dataset_dir(config, sensor, log=print)
  split = lambda s, kind='': np.asarray(arrays.load_split(d, s, sensor, kind))
  return d, split


def invert_all(params, depth, steps, seed, corruption='', desc='inverting'):
  """Every scan of ``depth`` (metres) restored by the library
  (evaluation.restore_batches: per-scan draws of ``seed``), concatenated:
  the encoded scans, the corrupted targets and invert's result."""
  from dusty_jax import evaluation
  batches = list(evaluation.restore_batches(params, depth, corruption=corruption,
                                            num_steps=steps, seed=seed, progress=True,
                                            desc=desc))
  keep = ('inv_depth', 'measurability', 'scan', 'points', 'valid', 'loss')
  res = {k: np.concatenate([b[4][k] for b in batches]) for k in keep}
  return (np.concatenate([b[2] for b in batches]),
          np.concatenate([b[3] for b in batches]), res)


def renders_drop(params, inv_depth):
  """Pixels the baseline renders as dropped (x_tilde within beta of ALPHA)."""
  from dusty_jax.codec import ALPHA
  return None if params.variant.has_measurability else inv_depth <= ALPHA + params.tolerance


def synthesis(params, config, split, a):
  """Table II by the library (evaluation.synthesis, as the evaluate tool), the
  baseline's beta tuned on as many validation scans first."""
  from dusty_jax import evaluation
  test = split('test')
  n = min(a.num_synthesis, len(test))
  tol = 0.0
  if not params.variant.has_measurability:
    tol = evaluation.tune_tolerance(params, split('val'), num=n, trials=a.tune_trials,
                                    points=a.points)
  rec = evaluation.synthesis(params, test, split('train'), num=n, points=a.points,
                             seeds=a.seeds, tolerance=tol, progress=True)
  rows = rec['rows'][evaluation.row_label(params, tol)]
  train_row = {k: v[0] for k, v in rec['rows'][evaluation.TRAINING_ROW].items()}
  return {'rows': rows, 'train_row': train_row, 'num': rec['num'], 'points': a.points,
          'seeds': a.seeds, 'tolerance': tol}


def disentangle(params, split, a, name):
  from dusty_jax.metrics import ground_truth
  sensor = params.sensor
  idx = np.arange(min(a.num_invert, len(split('test'))))
  obs, comp, prob = (split('test', k)[idx] for k in ('', 'complete', 'drop_prob'))
  *_, res = invert_all(params, obs, a.invert_steps, seed=0, desc=f'{name}: inverting')
  out = ground_truth.disentanglement(
      sensor, res['inv_depth'], res['measurability'], obs, comp, prob,
      renders_drop=renders_drop(params, res['inv_depth']))
  out.update(num=len(idx), steps=a.invert_steps)
  np.savez_compressed(os.path.join(a.workdir, name, 'study_inversion.npz'),
                      inv_depth=res['inv_depth'][:8], measurability=res['measurability'][:8])
  return out


def restoration(params, split, a, name):
  from dusty_jax import codec
  from dusty_jax.metrics import ground_truth, reconstruction
  sensor = params.sensor
  n = min(a.num_restore, len(split('test')))
  obs, comp = split('test')[:n], split('test', 'complete')[:n]
  out = {}
  for spec in CORRUPTIONS:
    clean, target, res = invert_all(params, obs, a.invert_steps, seed=7, corruption=spec,
                             desc=f'{name}: {spec}')
    errs = reconstruction.errors(obs, res, np.asarray(params.angles), sensor)
    vs_clean = {k: float(np.nanmean(v)) for k, v in errs.items() if k != 'count'}
    surface = np.asarray(codec.valid_depth(comp, sensor))
    vs_complete, coverage = ground_truth.completion(
        sensor, res['inv_depth'], comp, surface, renders_drop(params, res['inv_depth']))
    out[spec] = {'vs_clean': vs_clean, 'vs_complete': vs_complete,
                 'coverage_complete': coverage}
    if spec == CORRUPTIONS[0]:
      np.savez_compressed(os.path.join(a.workdir, name, 'study_restore.npz'),
                          clean=clean[:4], target=target[:4],
                          inv_depth=res['inv_depth'][:4],
                          measurability=res['measurability'][:4], complete=comp[:4])
  return out


def trade(params, split, a):
  import jax
  from dusty_jax import codec, inversion
  from dusty_jax.metrics import ground_truth
  sensor = params.sensor
  n = min(a.num_trade, len(split('test')))
  obs, comp, prob = (split('test', k)[:n] for k in ('', 'complete', 'drop_prob'))
  target = np.asarray(codec.encode(obs, sensor))
  rows = []
  for it in TRADE_ITERS:
    # One timed run after one that compiles.
    t = common.timed(lambda: jax.device_get(inversion.invert(params, target, num_steps=it)), 1)
    dt, res = t.median, t.result
    g = ground_truth.disentanglement(sensor, res['inv_depth'], res['measurability'],
                                     obs, comp, prob)
    rows.append({'iterations': it, 's_per_scan': dt / n,
                 'completion_mae_m': g['completion']['mae_m'],
                 'completion_abs_rel': g['completion']['abs_rel'],
                 'fit_mae_m': g['fit']['mae_m'], 'fit_abs_rel': g['fit']['abs_rel'],
                 'auc_surface': g['measurability']['auc_surface']})
    print(f'  {it:5d} iterations: completion AbsRel {rows[-1]["completion_abs_rel"]:.4f}, '
          f'fit AbsRel {rows[-1]["fit_abs_rel"]:.4f}, {dt / n:.2f} s/scan', flush=True)
  return {'rows': rows, 'num': n}


# ----------------------------------------------------------------------------
# Pictures and the report.
# ----------------------------------------------------------------------------


def picture_samples(models, path):
  import jax
  from dusty_jax import sampling, writers
  cols = []
  for params in models.values():
    out = jax.device_get(sampling.sample(params, jax.random.key(3), 4))
    cols.append(out)
  rows = []
  for i in range(4):
    rows.append([writers.inv_depth_tile(o['scan'][i]) for o in cols])
    rows.append([writers.inv_depth_tile(o['inv_depth'][i], alpha=-2.0) for o in cols])
    rows.append([writers.prob_tile(o['measurability'][i]) for o in cols])
  writers.save_grid(path, rows, scale=2)


def picture_reliability(results, params_by_model, path):
  plt = common.pyplot()
  fig, ax = plt.subplots(figsize=(5, 4.5))
  ax.plot([0, 1], [0, 1], 'k:', lw=1, label='perfectly calibrated')
  for model, r in results.items():
    if not params_by_model[model].variant.has_measurability:
      continue
    rel = r['disentangle']['measurability']['reliability']
    pred, truth = np.asarray(rel['pred'], float), np.asarray(rel['truth'], float)
    ok = np.isfinite(pred)
    ece = r['disentangle']['measurability']['ece']
    ax.plot(pred[ok], truth[ok], 'o-', label=f'{LABELS[model]} (ECE {ece:.3f})')
  ax.set_xlabel('predicted measurability (bin mean)')
  ax.set_ylabel('true return probability (bin mean)')
  ax.set_title('Measurability vs the simulator\'s truth')
  ax.legend(loc='upper left', fontsize=8)
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def picture_trade(trade_rows, path):
  plt = common.pyplot()
  its = [r['iterations'] for r in trade_rows]
  fig, ax = plt.subplots(figsize=(5.5, 4))
  ax.plot(its, [r['completion_abs_rel'] for r in trade_rows], 'o-', label='completion')
  ax.plot(its, [r['fit_abs_rel'] for r in trade_rows], 's-', label='fit (valid pixels)')
  ax.set_xscale('log')
  ax.set_xlabel('inversion iterations')
  ax.set_ylabel('AbsRel vs complete depth')
  for r in trade_rows:
    ax.annotate(f'{r["s_per_scan"]:.1f}s', (r['iterations'], r['completion_abs_rel']),
                textcoords='offset points', xytext=(0, 6), fontsize=7, ha='center')
  ax.set_title('DUSty-I inversion: error vs iterations (s/scan)')
  ax.legend()
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def picture_restoration(workdir, models, path):
  from dusty_jax import codec, writers
  rows = []
  for model, params in models.items():
    f = os.path.join(workdir, model, 'study_restore.npz')
    if not os.path.isfile(f):
      continue
    r = np.load(f)
    comp = np.asarray(codec.encode(r['complete'], params.sensor))
    for i in range(2):
      rows.append([writers.inv_depth_tile(r['clean'][i]),
                   writers.inv_depth_tile(r['target'][i]),
                   writers.inv_depth_tile(r['inv_depth'][i], alpha=-2.0),
                   writers.prob_tile(r['measurability'][i]),
                   writers.inv_depth_tile(comp[i])])
  if not rows:  # every model's restoration came from --reuse: nothing restored here
    print(f'no restorations computed in {workdir}: {os.path.basename(path)} not drawn')
    return None
  writers.save_grid(path, rows, scale=1)
  return path


def picture_kitti(params, path):
  """A real KITTI scan restored by the DUSty-I model; None without the data."""
  import jax
  from dusty_jax import codec, corrupt, inversion, writers
  from dusty_jax.data import kitti
  f = os.path.join(KITTI_SAMPLE, '000000.bin')
  if not os.path.isfile(f):
    return None
  depth, _ = kitti.load_scan(f, params.sensor)
  clean = np.asarray(codec.encode(depth, params.sensor))
  rows = []
  for spec in ('', 'drop:0.9', 'beams:4'):
    target = clean if not spec else np.asarray(
        corrupt.apply(spec, jax.random.key(0), clean[None], params.sensor))[0]
    res = jax.device_get(inversion.invert(params, target, num_steps=500))
    rows.append([writers.inv_depth_tile(clean), writers.inv_depth_tile(target),
                 writers.inv_depth_tile(res['inv_depth'], alpha=-2.0),
                 writers.prob_tile(res['measurability']),
                 writers.inv_depth_tile(res['scan'])])
  writers.save_grid(path, rows, scale=1)
  return f


def table2(results):
  from dusty_jax.metrics import records
  rows = {}
  for model, r in results.items():
    s = r['synthesis']
    label = LABELS[model] + (f' (beta {s["tolerance"]:.4f})' if s['tolerance'] else '')
    rows[label] = s['rows']
  first = next(iter(results.values()))['synthesis']
  rows['training set'] = {k: [v] for k, v in first['train_row'].items()}
  return records.format_table(rows)


def md_table(header, rows):
  lines = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
  lines += ['| ' + ' | '.join(str(c) for c in r) + ' |' for r in rows]
  return '\n'.join(lines)


def report(results, trade_result, trade_model, train_seconds, a, machine, kitti_file,
           kitti_model='dusty1', restoration_file='study_restoration.png'):
  f3 = lambda v: f'{v:.3f}'
  d_rows = []
  for model, r in results.items():
    d = r['disentangle']
    m = d['measurability']
    d_rows.append([LABELS[model], f3(d['completion']['mae_m']), f3(d['completion']['abs_rel']),
                   f'{100 * d["coverage"]:.1f}', f3(d['fit']['mae_m']),
                   f3(d['fit']['abs_rel']), f3(m['ece']), f3(m['ece_surface']),
                   f3(m['brier']), f3(m['brier_surface']), f3(m['auc']),
                   f3(m['auc_surface']), f3(m['auc_near']),
                   f3(m['auc_near_within_ring']) if 'auc_near_within_ring' in m else 'n/a',
                   f3(m['ece_near'])])
  r_rows = []
  for model, r in results.items():
    for spec, v in r['restoration'].items():
      c = v['vs_clean']
      g = v['vs_complete']
      r_rows.append([LABELS[model], spec, f'{c["cd"] * 1e4:.2f}', f3(c['abs_rel']),
                     f3(c['rmse']), f'{100 * c["delta1"]:.1f}', f3(g['abs_rel']),
                     f3(g['mae_m']), f'{100 * v["coverage_complete"]:.1f}'])
  # The baseline beside them: linear interpolation of the same scans and draws
  # (restore.py's beside_table3: the first 64 test scans, seed 7, as here).
  import restore  # a sibling script: only for this row
  linear = restore.beside_table3(num=a.num_restore)['kitti']['abs_rel_vs_clean_scan']
  for spec, v in linear.items():
    r_rows.append(['linear interpolation', spec, '', f3(v), '', '', '', '', ''])
  t_rows = [[r['iterations'], f3(r['completion_abs_rel']), f3(r['completion_mae_m']),
             f3(r['fit_abs_rel']), f'{r["s_per_scan"]:.2f}'] for r in trade_result['rows']]
  first = next(iter(results.values()))
  cfg = model_config('dusty1', a)
  lines = [
      '# Study: baseline vs DUSty-I vs DUSty-II on simulated scenes',
      '',
      f'Generated by `python benchmarks/study.py --workdir {a.workdir} --scale {a.scale}'
      f' --models {a.models}`'
      f' on {machine}. Training on the simulated default data (2000 HDL-64E scans,'
      ' 64x256, procedural scenes); evaluation on the simulated test split, whose'
      ' complete depth and true drop probability are known.',
      '',
      f'Scale `{a.scale}`: latent {cfg.latent_dim}, channels {cfg.ch_base}..{cfg.ch_max},'
      f' batch {cfg.batch_size}, {cfg.num_steps} steps each'
      f' ({cfg.num_steps * cfg.batch_size / 1000:.0f} kimg; the paper trains 25,000 kimg),'
      ' the authors\' training otherwise (eq-lr constants, R1 every step, their'
      ' DiffAugment).',
      '',
      ('Training time: ' + ', '.join(f'{LABELS[m]} {s / 60:.1f} min'
                                     for m, s in train_seconds.items()) + '.'
       if train_seconds else
       'Training time: not recorded (the runs were trained outside this script).'),
      '',
  ]
  if a.from_pretrained:
    lines += [f'Not trained in this run: {a.from_pretrained} (MODEL=shipped generator,'
              ' trained by an earlier run of this study with the same settings); ' +
              (f'with `--reuse {os.path.basename(a.reuse)}` their {", ".join(REUSED_SECTIONS)}'
               ' sections are that run\'s, the rest computed here.' if a.reuse else
               'every section computed here.'), '']
  presets = common.experiment('study')['PRESETS']
  for preset in sorted({RUNS[m][1] for m in results} - {'authors'}):
    runs = ', '.join(m for m in results if RUNS[m][1] == preset)
    lines += [f'{runs} (beyond the paper, dusty_jax/drops.py) add the `drops` preset'
              f' {preset!r}: {presets[preset]}.', '']
  lines += [
      f'## Synthesis (Table II layout; N = {first["synthesis"]["num"]} clouds of'
      f' {first["synthesis"]["points"]} points, {first["synthesis"]["seeds"]} seeds)',
      '',
      '```', table2(results), '```',
      '',
      f'## Disentanglement ({first["disentangle"]["num"]} test scans inverted,'
      f' {first["disentangle"]["steps"]} iterations)',
      '',
      'Completion: pixels the sensor dropped although a surface was in range;'
      ' fit: returned pixels. Errors of x_tilde in metres against the complete'
      ' depth. Coverage: completion pixels the model fills (the baseline renders'
      ' drops in its only output). Measurability: ECE against the true return'
      ' probability; Brier and ROC AUC against the observed returns; "surf." on'
      ' pixels with a surface in range only. The baseline\'s measurability is'
      ' 1 everywhere (it has none).',
      '',
      md_table(['model', 'compl. MAE m', 'compl. AbsRel', 'coverage %', 'fit MAE m',
                'fit AbsRel', 'ECE', 'ECE surf.', 'Brier', 'Brier surf.', 'AUC',
                'AUC surf.', 'AUC < 40 m', 'AUC < 40 m within rings', 'ECE < 40 m'], d_rows),
      '',
      '![reliability](study_reliability.png)',
      '',
      '## Restoration (Table III layout)',
      '',
      'Against the clean scan (its valid pixels; CD x1e4 on clouds in units of'
      ' 120 m) and against the complete depth (surface pixels the model covers).',
      '',
      md_table(['model', 'corruption', 'CD x1e4', 'AbsRel', 'RMSE m', 'd<1.25 %',
                'AbsRel vs complete', 'MAE m vs complete', 'coverage %'], r_rows),
      '',
      *([f'![restoration]({os.path.basename(restoration_file)})',
         '',
         'Rows: per model two test scans, drop 90%. Columns: clean scan, corrupted'
         ' input, x_tilde, measurability, complete depth.',
         ''] if restoration_file else []),
      f'## Inversion: iterations against error ({LABELS[trade_model]}, '
      f'{trade_result["num"]} scans)',
      '',
      md_table(['iterations', 'compl. AbsRel', 'compl. MAE m', 'fit AbsRel', 's per scan'],
               t_rows),
      '',
      '![trade](study_trade.png)',
      '',
      '## Samples',
      '',
      '![samples](study_samples.png)',
      '',
      'Columns: ' + ', '.join(LABELS[m] for m in results) + '. Per sample three'
      ' rows: the scan x, x_tilde, the measurability (baseline: 1).',
  ]
  if kitti_file:
    lines += ['', f'## A real KITTI scan restored by the simulated-data {LABELS[kitti_model]}', '',
              '![kitti](study_kitti.png)', '',
              'KITTI odometry sequence 00, frame 0. The model was trained on simulated'
              ' scenes only, never on KITTI. Rows: the scan as measured, 90% of points'
              ' dropped, 1 beam in 4. Columns: clean, input, x_tilde, measurability,'
              ' re-rendered scan.']
  return '\n'.join(lines) + '\n'


def main(argv=None):
  a = parse_args(argv)
  machine = common.print_banner()['banner']
  models = [m for m in a.models.split(',') if m]
  bad = [m for m in models if m not in MODELS]
  if bad:
    sys.exit(f'error: unknown models {bad}; known: {list(MODELS)}')
  seeded = dict(item.split('=', 1) for item in a.from_pretrained.split(',') if item)
  reuse = json.load(open(a.reuse)) if a.reuse else None
  for m, name in seeded.items():
    seed_from_pretrained(m, name, a, reuse)
  train_seconds = {}
  if reuse:
    train_seconds.update({m: reuse['train_seconds'][m] for m in seeded
                          if m in reuse.get('train_seconds', {})})
  times_path = os.path.join(a.workdir, 'train_seconds.json')
  if os.path.isfile(times_path):
    train_seconds.update(json.load(open(times_path)))
  if not a.eval_only:
    for m in [m for m in models if m not in seeded]:
      dt = train(m, a)
      train_seconds[m] = train_seconds.get(m, 0.0) + dt
      os.makedirs(a.workdir, exist_ok=True)
      json.dump(train_seconds, open(times_path, 'w'))
  if a.train_only:
    return
  import dusty_jax
  results, params_by_model = {}, {}
  for m in models:
    params, config = dusty_jax.load_checkpoint(os.path.join(a.workdir, m))
    _, split = load_data(config, params.sensor)
    cache = Cache(os.path.join(a.workdir, m, 'study_eval.json'))
    print(f'== evaluating {LABELS[m]}', flush=True)
    syn = cache.get('synthesis', lambda: synthesis(params, config, split, a))
    params = params.replace(tolerance=syn['tolerance'])
    params_by_model[m] = params
    results[m] = {
        'synthesis': syn,
        'disentangle': cache.get('disentangle', lambda: disentangle(params, split, a, m)),
        'restoration': cache.get('restoration', lambda: restoration(params, split, a, m)),
    }
    results[m]['seconds'] = cache.data['seconds']
  key = TRADE_RUN if TRADE_RUN in models else models[0]
  cache = Cache(os.path.join(a.workdir, key, 'study_eval.json'))
  params = params_by_model[key]
  config = dusty_jax.load_checkpoint(os.path.join(a.workdir, key))[1]
  _, split = load_data(config, params.sensor)
  trade_result = cache.get('trade', lambda: trade(params, split, a))
  os.makedirs(a.out, exist_ok=True)
  picture_samples(params_by_model, os.path.join(a.out, 'study_samples.png'))
  picture_reliability(results, params_by_model, os.path.join(a.out, 'study_reliability.png'))
  picture_trade(trade_result['rows'], os.path.join(a.out, 'study_trade.png'))
  restoration_file = picture_restoration(a.workdir, params_by_model,
                                         os.path.join(a.out, 'study_restoration.png'))
  variant = next((m for m in ('dusty1_levels', 'dusty1_dipdrops')
                  if m in params_by_model), key)
  kitti_file = picture_kitti(params_by_model[variant],
                             os.path.join(a.out, 'study_kitti.png'))
  text = report(results, trade_result, key, train_seconds, a, machine, kitti_file, variant,
                restoration_file)
  with open(os.path.join(a.out, 'study.md'), 'w') as f:
    f.write(text)
  common.write_json(os.path.join(a.out, 'study.json'),
                    {'scale': a.scale, 'train_seconds': train_seconds,
                     'results': results, 'trade': trade_result}, indent=1)
  print(text)
  if a.export:
    from dusty_jax import pretrained
    for m, name in EXPORT_NAMES.items():
      if m in params_by_model and m not in seeded:
        config = dusty_jax.load_checkpoint(os.path.join(a.workdir, m))[1]
        model, preset = RUNS[m]
        training = {'config': f'experiments/study.py:{model},{preset},{a.scale}',
                    'preset': preset, 'scale': a.scale,
                    'seed': int(config.seed), 'steps': int(config.num_steps),
                    'batch_size': int(config.batch_size),
                    'augment': config.augment, 'drops': config.drops.to_dict(),
                    'beyond_the_paper': preset != 'authors'}
        source = f'benchmarks/study.py --scale {a.scale} ({m})'
        options = os.path.join(a.workdir, m, 'encoder', 'options.json')
        if params_by_model[m].encoder is not None and os.path.isfile(options):
          # The run's encoder (train_encoder), with the options it trained with.
          opts = json.load(open(options))
          training['encoder'] = ('python -m dusty_jax.tools.train_encoder --workdir RUN ' +
                                 ' '.join(f'--{k}={v}' for k, v in opts.items()))
          source += ' + encoder'
        path = pretrained.export(params_by_model[m], name, source=source,
                                 training=training)
        print(f'exported {path} ({os.path.getsize(path) / 1e6:.2f} MB)')


if __name__ == '__main__':
  main()
