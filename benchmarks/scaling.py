"""Model only what a scene requires: DUSty's size, sensor, scene and training length.

    python benchmarks/scaling.py --workdir runs/scaling [--sensors kitti,vlp16:256]
        [--sizes c8-64_z64,...] [--seeds 0,1] [--steps N] [--only-train | --speed-again]

Trains the main command's recipe (experiments/synthetic.py: the authors'
training at the CPU scale, then drop levels fitted) for each cell of a grid,
(sensor, size, seed), each in its own run directory
(WORKDIR/SENSOR/SIZE/seedS), then measures each cell and writes one JSON
(``--out``/scaling.json) and one picture (scaling.png). Each cell's training
resumes where a killed call stopped; each of its evaluation sections is
cached in RUN/scaling_eval.json (study.py's Cache), so a rerun skips finished
work. The report covers every cell found under --workdir, so cells trained
by separate calls, one at a time, end in the one JSON.

The grid:
  * sensors: ``kitti`` (HDL-64E, 64x256, the default data) and ``vlp16:256``
    (a Velodyne VLP-16, 16 rings, narrowed to 256 columns, the same column
    count as kitti so that the two differ by rings alone), both on simulated
    scans. A sensor is PRESET or PRESET:WIDTH (dusty_jax.sensor.PRESETS).
  * sizes: ``cB-M_zL`` is channels B..M, latent L: SIZES, three widths by two
    latent sizes; c16-128_z128 is today's shipped size (MAIN_SIZE).
  * seeds: 0 for every size, also 1 for the smallest and the largest of SIZES
    (``--seeds`` gives the seeds of every chosen size instead).
Each config is experiments/synthetic.py's get_config() with the size, the
sensor, the seed and keep_every changed; its final_eval is off (this
script's evaluation covers it, on both splits and more scans).

Per cell, measured:
  * speed (in a subprocess of its own, RUN's config, data-parallel over the
    CPU devices the training command picks): parameters of G and D; FLOPs per
    train step (XLA's cost analysis of the compiled step, summed over
    devices); the step's median time over --step-repeats steps after a
    compiling warm-up (benchmarks/train_step.time_step); inversion of 1 and
    of 32 scans: INVERT_ITERS iterations timed (median of 2 after a warm-up
    each) and extrapolated linearly to --invert-steps (fixed cost + per-
    iteration cost, both fitted to the two counts); peak memory: that
    subprocess's own peak (common.peak_rss_mib) after the step timing
    (``peak_rss_train_mib``) and at its end, inversions included
    (``peak_rss_mib``);
  * on the validation split and on the test split: Table II
    (evaluation.synthesis, N = --num-synthesis at --points points, mean over
    --synthesis-seeds; with the training-set row); --num-restore scans
    inverted --invert-steps iterations (study.invert_all, i.e.
    evaluation.restore_batches): completion (x_tilde against the complete
    depth where the sensor dropped a surface) and drop placement (AUC on
    surfaces < 40 m, overall and within rings, and ECE:
    metrics.ground_truth); restoration AbsRel against the clean scan for
    each of CORRUPTIONS (seed 7's per-scan draws, as study.py);
  * scene kinds (test split): the simulator's urban, residential and rural
    scenes apart (data.synthetic.scene_kinds recovers each scan's kind from
    its seed): Table II of the model's samples against the test scans of that
    kind, beside the training-set row (the mixed training split against the
    same scans: what a perfect model of the mix scores), and restoration per
    kind (the same per-scan figures, averaged per kind). The models trained on
    the mix; the gap to the training-set row is what to compare across kinds.
  * length (the --length-run cell only, LENGTH_RUN by default: the main
    command's size on kitti): the test figures at every --keep-every steps of
    that run, drop levels fitted at each step as at its end (kept in
    RUN/length/stepN/).

The choice, per sensor, on the validation split (never on test): let L be
the largest size (most FLOPs per step) with figures, and CRITERION the
lower-is-better figures named below. For each metric m, the threshold
T_m is the worst value of L over its seeds (with one seed, its value: no
spread). A size S is within the seed spread of the largest when, for every
m, the mean of S over its seeds is <= T_m. The smallest such size (fewest
FLOPs per step) is named; L always qualifies, so a size is always named.
"""

from __future__ import annotations

import argparse
import glob
import importlib.util
import json
import os
import re
import subprocess
import sys
import time

import numpy as np

import common
import study
from dusty_jax import configs, parallel  # as train.py: importing these starts no backend

# The rest of the library (and train_step) is imported inside the functions
# that use it, after main's parallel.use_cpu_cores: the CPU device count must
# be set before JAX's first operation, which importing a module may start.

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
SIZES = ('c8-64_z64', 'c8-64_z128', 'c16-128_z64', 'c16-128_z128',
         'c32-256_z64', 'c32-256_z128')  # smallest first, largest last
MAIN_SIZE = 'c16-128_z128'  # experiments/synthetic.py's (the shipped models')
SENSORS = ('kitti', 'vlp16:256')
LENGTH_RUN = ('kitti', MAIN_SIZE, 0)  # the run whose checkpoints the length study scores
KEEP_EVERY = 500
CORRUPTIONS = ('drop:0.9', 'beams:4')
INVERT_BATCHES = (1, 32)
INVERT_ITERS = (10, 30)  # the iteration counts timed; the rest is extrapolated
# (section, figure): the figures the choice compares, each lower is better.
CRITERION = (('synthesis', '1nna'), ('synthesis', 'mmd'),
             ('restoration', 'drop:0.9'), ('restoration', 'beams:4'))
EVAL_FILE = 'scaling_eval.json'
SIZE_RE = re.compile(r'^c(\d+)-(\d+)_z(\d+)$')


def parse_args(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--workdir', default='runs/scaling')
  p.add_argument('--out', default=os.path.join(HERE, 'results'))
  p.add_argument('--sensors', default=','.join(SENSORS), help='PRESET or PRESET:WIDTH, ...')
  p.add_argument('--sizes', default=','.join(SIZES), help='cBASE-MAX_zLATENT, ...')
  p.add_argument('--seeds', default='',
                 help="seeds of every chosen size ('': 0, and 1 for SIZES' first and last; "
                      "with --speed-again, every seed trained)")
  p.add_argument('--steps', type=int, default=None, help="override the experiment's num_steps")
  p.add_argument('--keep-every', type=int, default=KEEP_EVERY,
                 help='checkpoints kept for the length study (config keep_every)')
  p.add_argument('--only-train', action='store_true', help='train the cells; measure nothing')
  p.add_argument('--speed-again', action='store_true',
                 help="time each chosen cell's speed again, in this call only (so that the "
                      "cells' step times compare: a shared machine's load varies between calls)")
  p.add_argument('--only-report', action='store_true',
                 help='train nothing, measure nothing: the report of what is cached')
  p.add_argument('--no-length', action='store_true', help='skip the length study')
  p.add_argument('--length-run', default='/'.join(map(str, LENGTH_RUN)),
                 help='SENSOR/SIZE/SEED: the cell whose checkpoints the length study scores')
  p.add_argument('--num-synthesis', type=int, default=200)
  p.add_argument('--points', type=int, default=512)
  p.add_argument('--synthesis-seeds', type=int, default=3)
  p.add_argument('--num-restore', type=int, default=64,
                 help='scans inverted per split (completion, placement, restoration)')
  p.add_argument('--invert-steps', type=int, default=300,
                 help="inversion iterations (the main command's final evaluation's)")
  p.add_argument('--step-repeats', type=int, default=10)
  p.add_argument('--set', action='append', default=[], metavar='FIELD=VALUE',
                 help='override a config field of every cell (tests: tiny data)')
  p.add_argument('--measure', default='', help=argparse.SUPPRESS)  # the speed subprocess
  return p.parse_args(argv)


# ----------------------------------------------------------------------------
# The grid and its configs.
# ----------------------------------------------------------------------------


def parse_size(size: str) -> tuple[int, int, int]:
  """(ch_base, ch_max, latent_dim) of a size name ``cB-M_zL``."""
  m = SIZE_RE.match(size)
  if not m:
    raise ValueError(f'size {size!r}: write cBASE-MAX_zLATENT, e.g. {MAIN_SIZE}')
  return tuple(int(g) for g in m.groups())


def parse_sensor(sensor: str) -> tuple[str, int]:
  """(preset, width; 0: the preset's) of PRESET or PRESET:WIDTH."""
  preset, _, width = sensor.partition(':')
  return preset, int(width) if width else 0


def sensor_dir(sensor: str) -> str:
  return sensor.replace(':', '-')


def cells(a) -> list[tuple[str, str, int]]:
  """(sensor, size, seed) of every chosen cell, in the order they train."""
  sizes = [s for s in a.sizes.split(',') if s]
  for s in sizes:
    parse_size(s)
  out = []
  for sensor in [s for s in a.sensors.split(',') if s]:
    for size in sizes:
      if a.seeds:
        seeds = [int(s) for s in a.seeds.split(',')]
      elif a.speed_again:  # every seed trained, whichever the defaults name
        tails = [p.rsplit('seed', 1)[1] for p in glob.glob(run_dir(a.workdir, sensor, size, '*'))]
        seeds = sorted(int(t) for t in tails if t.isdigit())
      else:
        seeds = [0, 1] if size in (SIZES[0], SIZES[-1]) else [0]
      out += [(sensor, size, seed) for seed in seeds]
  return out


def run_dir(workdir: str, sensor: str, size: str, seed: int | str) -> str:
  return os.path.join(workdir, sensor_dir(sensor), size, f'seed{seed}')


def experiment():
  """experiments/synthetic.py as a module (the main command's config)."""
  spec = importlib.util.spec_from_file_location(
      'synthetic_experiment', os.path.join(REPO, 'experiments', 'synthetic.py'))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def set_field(c, item: str):
  """Applies FIELD=VALUE (dotted) to config ``c``, VALUE cast to the field's type."""
  field, sep, value = item.partition('=')
  if not sep:
    raise ValueError(f'--set {item!r}: write FIELD=VALUE')
  *parents, last = field.split('.')
  node = c
  for p in parents:
    node = node[p]
  if last not in node:
    raise ValueError(f'--set {item!r}: the config has no field {field}')
  old = node[last]
  node[last] = (value.lower() in ('1', 'true') if isinstance(old, bool) else
                type(old)(value) if isinstance(old, (int, float, str)) else json.loads(value))


def cell_config(sensor: str, size: str, seed: int, a):
  c = experiment().get_config()
  c.sensor.preset, c.sensor.width = parse_sensor(sensor)
  c.ch_base, c.ch_max, c.latent_dim = parse_size(size)
  c.seed = seed
  c.keep_every = a.keep_every
  c.final_eval.num_synthesis = c.final_eval.num_invert = 0  # measured here instead
  if a.steps:
    c.num_steps = a.steps
  for item in a.set:
    set_field(c, item)
  return c


# ----------------------------------------------------------------------------
# Training and the speed subprocess.
# ----------------------------------------------------------------------------


def train(config, workdir: str) -> dict:
  # after use_cpu_cores (see the imports above)
  from dusty_jax import checkpoint, trainer
  before = checkpoint.saved_steps(workdir) if os.path.isdir(workdir) else []
  t = time.time()
  trainer.train_and_evaluate(config, workdir)
  return {'seconds': time.time() - t, 'resumed_from': int(before[-1]) if before else 0,
          'steps': int(config.num_steps),
          'note': 'wall seconds of the call that finished the run (from resumed_from)'}


def count(tree) -> int:
  # after use_cpu_cores (see the imports above)
  import jax
  return int(sum(np.prod(v.shape) for v in jax.tree.leaves(tree)))


def measure(run: str, a) -> dict:
  """The speed section of run directory ``run``; runs in its own process
  (main's --measure), whose peak memory it reports."""
  # after use_cpu_cores (see the imports above)
  import jax
  import jax.numpy as jnp
  import dusty_jax
  import train_step
  from dusty_jax import generator, inversion, sampling, trainer
  config = configs.load(run)
  sensor = generator.read_spec(run)[0]  # the spec the run recorded
  setup = trainer.make_setup(config, sensor)
  key = jax.random.key(0)
  g = jax.eval_shape(setup.generator.init, key, jnp.zeros((1, setup.settings.latent_dim)))
  d = jax.eval_shape(setup.discriminator.init, key, jnp.zeros((1,) + sensor.shape))
  timing, flops = train_step.time_step(config, sensor, a.step_repeats)
  out = {'params_g': count(g), 'params_d': count(d), 'flops_per_step': flops,
         'step_s': timing.median, 'step_times_s': timing.times,
         'step_compile_s': timing.warmup[0], 'devices': jax.device_count(),
         'peak_rss_train_mib': common.peak_rss_mib()}
  params, _ = dusty_jax.load_checkpoint(run, log=lambda m: None)
  out['invert'] = {}
  for b in INVERT_BATCHES:
    target = sampling.sample(params, jax.random.key(7), b)['scan']
    t = {it: common.timed(lambda: inversion.invert(params, target, num_steps=it), 2).median
         for it in INVERT_ITERS}
    lo, hi = INVERT_ITERS
    per_iter = (t[hi] - t[lo]) / (hi - lo)
    fixed = max(t[lo] - lo * per_iter, 0.0)
    out['invert'][str(b)] = {'timed_s': {str(k): v for k, v in t.items()},
                             'per_iteration_s': per_iter, 'fixed_s': fixed,
                             'iterations': a.invert_steps,
                             'seconds': fixed + a.invert_steps * per_iter}
  out['invert_note'] = (f'{INVERT_ITERS} iterations timed (median of 2 after a warm-up '
                        f'each), extrapolated linearly to {a.invert_steps}')
  out['peak_rss_mib'] = common.peak_rss_mib()
  out['machine'] = common.machine()
  out['load_average_1min'] = os.getloadavg()[0]  # at the end: what else ran
  out['peak_rss_note'] = ('VmHWM of the measuring subprocess: after the step timing '
                          '(train), and at its end (inversions of 1 and 32 scans too)')
  return out


def measure_in_subprocess(run: str, a) -> dict:
  cmd = [sys.executable, os.path.abspath(__file__), '--measure', run,
         '--step-repeats', str(a.step_repeats), '--invert-steps', str(a.invert_steps)]
  # This checkout's library, whatever the environment's PYTHONPATH says.
  env = dict(os.environ, PYTHONPATH=os.pathsep.join(
      [REPO] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]))
  proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
  if proc.returncode:
    raise RuntimeError(f'measuring {run} failed ({proc.returncode}):\n{proc.stderr[-3000:]}')
  return json.loads(proc.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------
# Evaluation: one split of one generator.
# ----------------------------------------------------------------------------


def table2(params, depth, train_depth, a) -> dict:
  # after use_cpu_cores (see the imports above)
  from dusty_jax import evaluation
  rec = evaluation.synthesis(params, depth, train_depth, num=min(a.num_synthesis, len(depth)),
                             points=a.points, seeds=a.synthesis_seeds)
  rows = rec['rows'][evaluation.row_label(params, rec['tolerance'])]
  return {'num': rec['num'], 'points': a.points, 'seeds': a.synthesis_seeds,
          'mean': {k: float(np.mean(v)) for k, v in rows.items()},
          'per_seed': rows,
          'train_row': {k: v[0] for k, v in rec['rows'][evaluation.TRAINING_ROW].items()}}


def evaluate(params, split, which: str, a, kinds=None) -> dict:
  """Table II, completion, drop placement and restoration of ``params`` on
  split ``which``; with ``kinds`` (a scene kind per scan), also per kind."""
  # after use_cpu_cores (see the imports above)
  from dusty_jax.metrics import ground_truth, reconstruction
  sensor, angles = params.sensor, np.asarray(params.angles)
  depth, train_depth = split(which), split('train')
  out = {'split': which, 'synthesis': table2(params, depth, train_depth, a)}
  n = min(a.num_restore, len(depth))
  obs, comp, prob = depth[:n], split(which, 'complete')[:n], split(which, 'drop_prob')[:n]
  *_, res = study.invert_all(params, obs, a.invert_steps, seed=0, desc=f'{which}: inverting')
  g = ground_truth.disentanglement(sensor, res['inv_depth'], res['measurability'],
                                   obs, comp, prob)
  m = g['measurability']
  out['inverted'] = {'num': n, 'steps': a.invert_steps, 'completion': g['completion'],
                     'coverage': g['coverage'], 'fit': g['fit'],
                     'placement': {k: m[k] for k in ('auc_near', 'auc_near_within_ring',
                                                     'auc_surface', 'ece', 'ece_near')}}
  per_scan = {}
  for spec in CORRUPTIONS:
    *_, res = study.invert_all(params, obs, a.invert_steps, seed=7, corruption=spec,
                               desc=f'{which}: {spec}')
    per_scan[spec] = reconstruction.errors(obs, res, angles, sensor)['abs_rel']
  out['restoration'] = {'num': n, 'steps': a.invert_steps, 'metric': 'AbsRel vs clean scan',
                        **{s: float(np.nanmean(v)) for s, v in per_scan.items()}}
  if kinds is not None:
    out['kinds'] = {}
    for kind in sorted(set(kinds)):
      idx = np.flatnonzero(kinds == kind)
      sub = idx[idx < n]
      out['kinds'][kind] = {
          'scans': int(len(idx)),
          'synthesis': table2(params, depth[idx], train_depth, a) if len(idx) >= 2 else None,
          'restoration': {'num': int(len(sub)),
                          **{s: float(np.nanmean(v[sub])) if len(sub) else None
                             for s, v in per_scan.items()}}}
  return out


def with_fitted_levels(params, train_depth, where: str, step: int):
  """``params`` with drop levels fitted as at the end of training, kept in
  ``where`` (levels.FILE) so that a rerun does not fit them again."""
  # after use_cpu_cores (see the imports above)
  from dusty_jax import evaluation, levels
  kept = levels.load(where)
  if kept is not None and kept[1] == step:
    return levels.with_levels(levels.without_levels(params), kept[0])
  fitted = evaluation.fit_levels(params, train_depth)
  os.makedirs(where, exist_ok=True)
  levels.save(where, fitted.variables['params']['depth_levels'], step)
  return fitted


def evaluate_cell(run: str, a, length: bool):
  # after use_cpu_cores (see the imports above)
  import dusty_jax
  from dusty_jax import checkpoint
  from dusty_jax.data import synthetic
  cache = study.Cache(os.path.join(run, EVAL_FILE))
  cache.get('speed', lambda: measure_in_subprocess(run, a))
  params, config = dusty_jax.load_checkpoint(run, log=lambda m: None)
  data_dir, split = study.load_data(config, params.sensor)
  cache.get('val', lambda: evaluate(params, split, 'val', a))
  kinds = synthetic.scene_kinds(data_dir, 'test')
  if len(kinds) != len(split('test')):
    raise ValueError(f'{data_dir}: {len(kinds)} scene kinds for {len(split("test"))} test scans')
  test = cache.get('test', lambda: evaluate(params, split, 'test', a, kinds))
  if not length:
    return
  last = int(config.num_steps)
  for step in checkpoint.saved_steps(run):
    if step % a.keep_every or step >= last:
      continue
    def at_step(step=step):
      p, _ = dusty_jax.load_checkpoint(run, step=step, log=lambda m: None)
      p = with_fitted_levels(p, split('train'), os.path.join(run, 'length', f'step{step:07d}'),
                             step)
      return evaluate(p, split, 'test', a)
    cache.get(f'length_{step:07d}', at_step)
  cache.get(f'length_{last:07d}', lambda: test)


# ----------------------------------------------------------------------------
# The choice, the report, the picture.
# ----------------------------------------------------------------------------


def figure(ev: dict, section: str, name: str) -> float:
  return ev[section]['mean'][name] if section == 'synthesis' else ev[section][name]


def smallest_within_spread(sizes: dict) -> dict:
  """The module docstring's rule. ``sizes``: {size: {'flops': per step,
  'values': {metric: [one value per seed]}}}, lower better. Returns the
  named size, the largest, the thresholds and each size's verdict."""
  largest = max(sizes, key=lambda s: sizes[s]['flops'])
  thresholds = {m: max(v) for m, v in sizes[largest]['values'].items()}
  verdicts = {}
  for s, v in sizes.items():
    means = {m: float(np.mean(v['values'][m])) for m in thresholds}
    verdicts[s] = {'means': means, 'seeds': len(next(iter(v['values'].values()))),
                   'within': all(means[m] <= thresholds[m] for m in thresholds)}
  within = [s for s in sizes if verdicts[s]['within']]
  return {'smallest': min(within, key=lambda s: sizes[s]['flops']), 'largest': largest,
          'thresholds': thresholds, 'verdicts': verdicts}


def collect(workdir: str) -> dict:
  """{'SENSOR/SIZE/seedS': cache} of every run under ``workdir`` with figures."""
  out = {}
  for path in sorted(glob.glob(os.path.join(workdir, '*', '*', 'seed*', EVAL_FILE))):
    rel = os.path.relpath(os.path.dirname(path), workdir)
    out[rel.replace(os.sep, '/')] = json.load(open(path))
  return out


def choose(results: dict) -> dict:
  """Per sensor, smallest_within_spread on the validation figures."""
  by_sensor = {}
  for key, r in results.items():
    sensor, size, _ = key.split('/')
    if 'val' not in r or 'speed' not in r:
      continue
    entry = by_sensor.setdefault(sensor, {}).setdefault(
        size, {'flops': r['speed']['flops_per_step'], 'values': {}})
    for section, name in CRITERION:
      entry['values'].setdefault(f'{section}.{name}', []).append(figure(r['val'], section, name))
  return {s: smallest_within_spread(v) for s, v in by_sensor.items()}


def rows(results: dict) -> list[list[str]]:
  out = []
  for key, r in results.items():
    sp, te = r.get('speed'), r.get('test')
    if not sp or not te:
      continue
    out.append([key, f'{(sp["params_g"] + sp["params_d"]) / 1e6:.2f}',
                f'{sp["flops_per_step"] / 1e9:.1f}', f'{sp["step_s"]:.3f}',
                f'{sp["invert"]["1"]["seconds"]:.1f}', f'{sp["invert"]["32"]["seconds"]:.1f}',
                f'{sp["peak_rss_mib"]:.0f}',
                f'{100 * te["synthesis"]["mean"]["1nna"]:.1f}',
                f'{1e3 * te["synthesis"]["mean"]["mmd"]:.2f}',
                *(f'{te["restoration"][c]:.3f}' for c in CORRUPTIONS),
                f'{te["inverted"]["completion"]["abs_rel"]:.3f}',
                f'{te["inverted"]["placement"]["auc_near"]:.3f}',
                f'{te["inverted"]["placement"]["auc_near_within_ring"]:.3f}'])
  return out


HEADER = ['cell', 'params M (G+D)', 'GFLOP/step', 'step s', 'invert 1 s', 'invert 32 s',
          'peak MiB', '1-NNA %', 'MMD x1e3', *(f'AbsRel {c}' for c in CORRUPTIONS),
          'compl. AbsRel', 'AUC < 40 m', 'AUC < 40 m in rings']


def summary(results: dict, chosen: dict, a, machine: str) -> str:
  lines = [f'# Scaling: DUSty size, sensor, scene, length ({machine})', '',
           'Test split; speed with --invert-steps '
           f'{a.invert_steps} iterations (extrapolated from {INVERT_ITERS}).', '',
           study.md_table(HEADER, rows(results)), '']
  for sensor, c in chosen.items():
    lines.append(f'- {sensor}: smallest within the seed spread of {c["largest"]} on '
                 f'validation: **{c["smallest"]}** (criterion {[f"{s}.{n}" for s, n in CRITERION]})')
  kind_rows = []
  for key, r in results.items():
    for kind, k in r.get('test', {}).get('kinds', {}).items():
      syn = k['synthesis']
      kind_rows.append([key, kind, k['scans'],
                        f'{100 * syn["mean"]["1nna"]:.1f} ({100 * syn["train_row"]["1nna"]:.1f})'
                        if syn else 'n/a',
                        f'{1e3 * syn["mean"]["mmd"]:.2f} ({1e3 * syn["train_row"]["mmd"]:.2f})'
                        if syn else 'n/a',
                        *(f'{k["restoration"][c]:.3f}' if k['restoration'][c] is not None
                          else 'n/a' for c in CORRUPTIONS)])
  if kind_rows:
    lines += ['', 'Per scene kind (test): 1-NNA % and MMD of the samples against that kind\'s '
              'scans (training-set row in brackets), restoration AbsRel.', '',
              study.md_table(['cell', 'kind', 'scans', '1-NNA % (train row)', 'MMD x1e3 (train row)',
                              *(f'AbsRel {c}' for c in CORRUPTIONS)], kind_rows)]
  return '\n'.join(lines) + '\n'


def length_points(results: dict, length_run: str) -> list[dict]:
  sensor, size, seed = length_run.split('/')
  r = results.get(f'{sensor_dir(sensor)}/{size}/seed{seed}', {})
  return [{'step': int(k.split('_')[1]), '1nna': v['synthesis']['mean']['1nna'],
           'mmd': v['synthesis']['mean']['mmd'], **{c: v['restoration'][c] for c in CORRUPTIONS}}
          for k, v in sorted(r.items()) if k.startswith('length_')]


# (section, figure, label, scale) of the picture's quality panels: the figures
# that separate the sizes (1-NNA is near 100% for every CPU-scale model;
# beams:4 separates them more than drop:0.9).
PANELS = (('synthesis', 'mmd', 'MMD x1e3 (test)', 1e3),
          ('restoration', 'beams:4', 'restoration AbsRel, beams:4 (test)', 1.0))


# Where label_points may put a name: (x, y) offset in points, alignment.
LABEL_PLACES = tuple(((dx, dy), ha, 'bottom' if dy > 0 else 'top')
                     for d in (4, 14) for dx, ha in ((3, 'left'), (-3, 'right'), (0, 'center'))
                     for dy in (d, -d))


def label_points(ax, points):
  """Names each (x, y, name, colour) point at the place of LABEL_PLACES (the
  first, on a tie) whose text box stays in the axes, overlaps the fewest
  names already placed, then crosses the fewest line pieces and error bars;
  a place of the outer ring counts as three crossings. Sizes one step time
  apart would otherwise print over each other. Call it after the figure's
  layout: it works in pixels."""
  renderer = ax.figure.canvas.get_renderer()
  segments = [ax.transData.transform(line.get_xydata()) for line in ax.lines]
  segments += [ax.transData.transform(seg) for c in ax.collections for seg in c.get_segments()]
  drawn = [a + np.linspace(0, 1, 30)[:, None] * (b - a)  # each straight piece, sampled
           for seg in segments for a, b in zip(seg, seg[1:])]
  taken = []
  for x, y, name, colour in points:
    best = None
    for offset, ha, va in LABEL_PLACES:
      text = ax.annotate(name, (x, y), textcoords='offset points', xytext=offset,
                         ha=ha, va=va, fontsize=7, color=colour)
      box = text.get_window_extent(renderer).padded(2)
      inside = lambda p: np.any((p[:, 0] > box.x0) & (p[:, 0] < box.x1) &
                                (p[:, 1] > box.y0) & (p[:, 1] < box.y1))
      clashes = (100 * (box.x0 < ax.bbox.x0 or box.x1 > ax.bbox.x1 or
                        box.y0 < ax.bbox.y0 or box.y1 > ax.bbox.y1) +
                 10 * sum(box.overlaps(b) for b in taken) + sum(map(inside, drawn)) +
                 3 * (abs(offset[1]) > 4))  # far from its point: worse than crossing a line
      if best is None or clashes < best[0]:
        if best:
          best[1].remove()
        best = (clashes, text, box)
      else:
        text.remove()
      if clashes == 0:
        break
    taken.append(best[2])


def linear_baselines(corruption: str) -> dict:
  """{sensor: linear interpolation's AbsRel against the clean scan} of the
  same test scans and corruption (benchmarks/restore.py's beside_table3,
  from results/restore.json); {} where it was not measured."""
  path = os.path.join(HERE, 'results', 'restore.json')
  if not os.path.isfile(path):
    return {}
  with open(path) as f:
    table = json.load(f).get('linear_beside_table3', {})
  return {s: v['abs_rel_vs_clean_scan'][corruption] for s, v in table.items()
          if corruption in v['abs_rel_vs_clean_scan']}


def picture(results: dict, length: list, length_run: str, path: str):
  """Quality against step time, a line per sensor (a panel per PANELS
  figure; bars: the seeds' range), and the length run's figures against its
  training steps."""
  plt = common.pyplot()
  fig, axes = plt.subplots(1, len(PANELS) + 1, figsize=(5 * (len(PANELS) + 1), 4.2))
  labels = []
  for ax, (section, name, label, scale) in zip(axes, PANELS):
    by_sensor, points = {}, []
    for key, r in results.items():
      if 'speed' in r and 'test' in r:
        sensor, size, _ = key.split('/')
        by_sensor.setdefault(sensor, {}).setdefault(size, []).append(
            (r['speed']['step_s'], scale * figure(r['test'], section, name)))
    for sensor, sizes in sorted(by_sensor.items()):
      pts = sorted((np.mean([p[0] for p in v]), np.mean([p[1] for p in v]),
                    min(p[1] for p in v), max(p[1] for p in v), s) for s, v in sizes.items())
      x, y, lo, hi, names = map(np.asarray, zip(*pts))
      line = ax.errorbar(x, y, yerr=[y - lo, hi - y], fmt='o-', capsize=3, label=sensor)
      points += [(xi, yi, n, line[0].get_color()) for xi, yi, n in zip(x, y, names)]
    if section == 'restoration':  # linear interpolation of the same scans (restore.py)
      for sensor, linear in linear_baselines(name).items():
        if sensor in by_sensor:
          ax.axhline(scale * linear, ls=':', color='grey')
          ax.annotate(f'linear interpolation, {sensor}', (1, scale * linear), fontsize=7,
                      xycoords=('axes fraction', 'data'), ha='right', va='bottom', color='grey')
    ax.set_xscale('log')
    labels.append((ax, points))
    ax.xaxis.set_minor_formatter(plt.NullFormatter())  # minor labels overlap past a decade
    ax.xaxis.set_major_formatter(plt.FuncFormatter(lambda v, _: f'{v:g}'))
    ax.set_xticks([t for t in (0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5)
                   if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]])
    ax.set_xlabel('seconds per train step (log)')
    ax.set_ylabel(label + '; lower is better')
    ax.set_title(f'{label.split(" (")[0]} against step time')
    ax.legend(fontsize=8)
  ax = axes[-1]
  if length:
    steps = [p['step'] for p in length]
    ax.plot(steps, [1e3 * p['mmd'] for p in length], 'o-', label='MMD x1e3')
    ax.set_ylabel('MMD x1e3 (test)')
    twin = ax.twinx()
    for i, (c, mark) in enumerate(zip(CORRUPTIONS, 'sd')):
      twin.plot(steps, [p[c] for p in length], mark + '--', label=f'AbsRel {c}', color=f'C{1 + i}')
    twin.set_yscale('log')  # an untrained model restores at AbsRel > 1
    twin.set_ylabel('restoration AbsRel (test, log)')
    handles = ax.get_legend_handles_labels()[0] + twin.get_legend_handles_labels()[0]
    ax.legend(handles=handles, loc='center right', fontsize=8)
  sensor, size, seed = length_run.split('/')
  ax.set_xlabel('training steps')
  ax.set_title(f'Length: {sensor} {size} seed {seed}' + ('' if length else ' (not run)'))
  fig.tight_layout()
  for ax, points in labels:
    label_points(ax, points)
  fig.savefig(path, dpi=120)
  plt.close(fig)


def main(argv=None):
  a = parse_args(argv)
  if a.measure:
    parallel.use_cpu_cores(configs.load(a.measure).batch_size)
    print(json.dumps(measure(a.measure, a)))
    return None
  chosen_cells = cells(a)
  if a.speed_again:  # times trained cells only
    chosen_cells = [c for c in chosen_cells if 'train' in study.Cache(
        os.path.join(run_dir(a.workdir, *c), EVAL_FILE)).data]
    if not chosen_cells:
      raise SystemExit(f'--speed-again: no trained cell of --sensors {a.sensors} '
                       f'--sizes {a.sizes} under {a.workdir}')
  if not a.only_report:
    # Before JAX's first operation, as the training command (train.py).
    parallel.use_cpu_cores(cell_config(*chosen_cells[0], a).batch_size)
  machine = common.machine()
  print(machine['banner'], flush=True)
  if not a.only_report:
    for sensor, size, seed in chosen_cells:
      run = run_dir(a.workdir, sensor, size, seed)
      cache = study.Cache(os.path.join(run, EVAL_FILE))
      if 'train' not in cache.data:
        print(f'== training {sensor} {size} seed {seed} into {run}', flush=True)
      cache.get('train', lambda: train(cell_config(sensor, size, seed, a), run))
      if a.only_train:
        continue
      if a.speed_again:
        print(f'== timing {sensor} {size} seed {seed} again', flush=True)
        cache.data.pop('speed', None)
        cache.get('speed', lambda: measure_in_subprocess(run, a))
        continue
      print(f'== measuring {sensor} {size} seed {seed}', flush=True)
      length = not a.no_length and f'{sensor}/{size}/{seed}' == a.length_run
      evaluate_cell(run, a, length)
    if a.only_train:
      return None
  results = collect(a.workdir)
  chosen = choose(results)
  length = length_points(results, a.length_run)
  os.makedirs(a.out, exist_ok=True)
  picture(results, length, a.length_run, os.path.join(a.out, 'scaling.png'))
  text = summary(results, chosen, a, machine['banner'])
  record = {'command': ' '.join([os.path.basename(sys.argv[0]) or 'scaling.py'] +
                                (sys.argv[1:] if argv is None else list(argv))),
            'criterion': {'metrics': [f'{s}.{n}' for s, n in CRITERION],
                          'split': 'val', 'rule': 'module docstring'},
            'cells': results, 'chosen': chosen, 'length': length, 'summary_md': text}
  path = common.write_json(os.path.join(a.out, 'scaling.json'), record, indent=1)
  print(text)
  print(f'written: {path}, {os.path.join(a.out, "scaling.png")}')
  return record


if __name__ == '__main__':
  main()
