"""Screening the point-drop mechanisms: short DUSty-I trainings, side by side.

    python benchmarks/research/drops/drops_screen.py --workdir runs/screen [--steps 600]
        [--variants authors,rate,...] [--out benchmarks/research/drops/results]

Each variant is the study's CPU-scale DUSty-I (experiments/study.py)
with some of the ``drops`` options of dusty_jax/configs.py set (VARIANTS
below), trained for ``--steps`` (resumable: a rerun continues, or only
evaluates what is done). For each it reports, over training:
  * the drop rate of the generated scans, and D's mean logits (metrics.jsonl);
  * the correlation of the EMA generator's per-ring drop rate (64 samples)
    with the training data's, at every kept checkpoint: a cheap signal of
    *where* the drops go, not only how many;
and at the end, on held-out simulated test scans inverted by the EMA
generator, the measurability against the simulator's truth: ROC AUC against
the observed drops on surfaces nearer than 40 m (the target: > 0.75), on all
surfaces, ECE, and the completion / fit errors.

Writes ``drops_screen.json`` and ``drops_screen.png`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

# benchmarks/ holds common.py, shared with the product benchmarks.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..'))
import common

HERE = os.path.dirname(os.path.abspath(__file__))
KEEP_RATE_LOGIT = 1.386  # logit(0.8): the simulated scans keep ~80% of pixels.

# Pieces of the variants below.
CHANNEL = {'mask_channel': 1.0, 'mask_noise': 0.1, 'mask_dropout': 0.5}
RING_DEPTH = {'mask_bias': KEEP_RATE_LOGIT, 'ring_bias': True}  # (rate_by='ring_depth')

VARIANTS = {
    'authors': {},
    'rate': {'rate_weight': 10.0},
    'rate_bias': {'rate_weight': 10.0, 'mask_bias': KEEP_RATE_LOGIT},
    'ring_rate_bias': {'rate_weight': 10.0, 'rate_by': 'ring',
                       'mask_bias': KEEP_RATE_LOGIT},
    'keep_drops_bias': {'keep_drops': True, 'mask_bias': KEEP_RATE_LOGIT},
    'mask_channel': dict(CHANNEL),
    'slow_mask_bias': {'mask_lr': 0.1, 'mask_bias': KEEP_RATE_LOGIT},
    'channel_rate_slow': {**CHANNEL, 'rate_weight': 10.0, 'mask_bias': KEEP_RATE_LOGIT,
                          'mask_lr': 0.1},
    'channel_keep_rate': {'mask_channel': 0.5, 'mask_noise': 0.1, 'mask_dropout': 0.5,
                          'keep_drops': True, 'rate_weight': 10.0,
                          'mask_bias': KEEP_RATE_LOGIT},
    'rate1_bias': {'rate_weight': 1.0, 'mask_bias': KEEP_RATE_LOGIT},
    'rate100_bias': {'rate_weight': 100.0, 'mask_bias': KEEP_RATE_LOGIT},
    'channel_rate_bias': {**CHANNEL, 'rate_weight': 10.0, 'mask_bias': KEEP_RATE_LOGIT},
    'keep_rate_bias': {'keep_drops': True, 'rate_weight': 10.0,
                       'mask_bias': KEEP_RATE_LOGIT},
    'dusty2_rate_bias': {'model': 'dusty2', 'rate_weight': 10.0,
                         'mask_bias': KEEP_RATE_LOGIT},
    'dusty2_authors': {'model': 'dusty2'},
    # A learned measurability offset per ring (laser), started at the data's
    # keep rate of that ring.
    'channel_rate_ring_bias': {**CHANNEL, 'rate_weight': 10.0, 'mask_bias': KEEP_RATE_LOGIT,
                               'ring_bias': True},
    'channel_ringrate_ring_bias': {**CHANNEL, 'rate_weight': 10.0, 'rate_by': 'ring',
                                   'mask_bias': KEEP_RATE_LOGIT, 'ring_bias': True},
    'channel_ringrate100_ring_bias': {**CHANNEL, 'rate_weight': 100.0, 'rate_by': 'ring',
                                      'mask_bias': KEEP_RATE_LOGIT, 'ring_bias': True},
    # The rate per (ring, depth of the returned neighbours) cell: drops may
    # depend on the range within a ring.
    'channel_ringdepth100_ring_bias': {**CHANNEL, **RING_DEPTH, 'rate_weight': 100.0},
    'channel_ringdepth_ring_bias': {**CHANNEL, **RING_DEPTH, 'rate_weight': 10.0},
    'ringdepth100_ring_bias': {**RING_DEPTH, 'rate_weight': 100.0},
    'ringdepth1000_ring_bias': {**RING_DEPTH, 'rate_weight': 1000.0},
    # Cell targets shrunk towards their ring's rate (as if 10 more pixels
    # kept at it): sparse cells no longer pull towards a noisy 0 or 1.
    'ringdepth100_shrink_ring_bias': {**RING_DEPTH, 'rate_weight': 100.0, 'rate_shrink': 10.0},
    # The rate term trains only the measurability head (on its expected keep
    # rate), leaving G's trunk to the GAN loss.
    'ringdepth100_head_ring_bias': {**RING_DEPTH, 'rate_weight': 100.0, 'rate_head_only': True},
    'channel_ringdepth100_head_ring_bias': {**CHANNEL, **RING_DEPTH, 'rate_weight': 100.0,
                                            'rate_head_only': True},
    # ... and no gradient of the mask (the GAN's straight-through one either)
    # reaches the trunk: it learns from x_tilde alone.
    'ringdepth100_detached_ring_bias': {**RING_DEPTH, 'rate_weight': 100.0,
                                        'rate_head_only': True, 'mask_detached': True},
    'dusty2_detached_ring_bias': {'model': 'dusty2', **RING_DEPTH, 'rate_weight': 100.0,
                                  'rate_head_only': True, 'mask_detached': True},
    'ringrate_ring_bias': {'rate_weight': 10.0, 'rate_by': 'ring',
                           'mask_bias': KEEP_RATE_LOGIT, 'ring_bias': True},
}


def config_of(variant: str, steps: int, every: int, data_dir: str = ''):
  from dusty_jax import configs
  options = dict(VARIANTS[variant])
  c = configs.study(options.pop('model', 'dusty1'))
  c.drops.update(options)
  c = configs.upgrade(c)  # options removed since (f597033 has them) are refused
  c.data.dir = data_dir
  c.num_steps = steps
  c.log_every = 10
  c.checkpoint_every = every
  c.keep_checkpoints = steps // every + 1
  c.image_every = steps
  return c


def ring_drop_rate(scans) -> np.ndarray:
  from dusty_jax.codec import ALPHA
  return (np.asarray(scans) <= ALPHA).mean(axis=(0, 2))


def curves(workdir: str, real_rings, num: int = 64) -> dict:
  """Training metrics and, per kept checkpoint, the EMA's ring correlation."""
  import jax
  from dusty_jax import checkpoint, generator, sampling
  recs = {}
  with open(os.path.join(workdir, 'metrics.jsonl')) as f:
    for line in f:
      m = json.loads(line)
      recs[m['step']] = m
  steps = sorted(recs)
  out = {k: [recs[s][k] for s in steps] for k in ('drop_rate', 'real_drop_rate',
                                                  'd_real', 'd_fake')}
  out['step'] = steps
  mngr = checkpoint.manager(workdir, keep=1000)
  out['ring_step'], out['ring_corr'], out['ema_drop_rate'] = [], [], []
  for s in sorted(mngr.all_steps()):
    if s == 0:
      continue
    params, _ = generator.load(workdir, step=s, log=lambda *_: None)
    scans = sampling.sample_scans(params, jax.random.key(7), num)
    rings = ring_drop_rate(scans)
    out['ring_step'].append(int(s))
    out['ring_corr'].append(float(np.corrcoef(rings, real_rings)[0, 1])
                            if rings.std() > 0 else float('nan'))
    out['ema_drop_rate'].append(float(rings.mean()))
  return out


def evaluate(workdir: str, split, num: int, steps: int, params=None) -> dict:
  """Disentanglement of held-out test scans inverted by the run's (latest)
  EMA generator, or by ``params`` if given."""
  import jax
  from dusty_jax import codec, generator, inversion
  from dusty_jax.metrics import ground_truth
  if params is None:
    params, _ = generator.load(workdir, log=lambda *_: None)
  idx = np.arange(num)
  obs, comp, prob = (np.asarray(split('test', k)[idx]) for k in
                     ('', 'complete', 'drop_prob'))
  keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(0), i))(idx)
  res = inversion.invert(params, np.asarray(codec.encode(obs, params.sensor)),
                         key=keys, num_steps=steps)
  out = ground_truth.disentanglement(params.sensor, np.asarray(res['inv_depth']),
                                     np.asarray(res['measurability']), obs, comp, prob)
  out['measurability'].pop('reliability')
  return out


def ring_prior(split, sensor, num: int, real_keep) -> dict:
  """The measurability scores of a constant: each ring's keep rate in the
  training scans, on the same held-out scans. What a model gains over it is
  what it learned beyond which laser a pixel belongs to."""
  from dusty_jax.metrics import ground_truth
  obs, comp, prob = (np.asarray(split('test', k)[:num]) for k in ('', 'complete', 'drop_prob'))
  m = np.broadcast_to(np.asarray(real_keep)[None, :, None], obs.shape)
  out = ground_truth.measurability_scores(sensor, m, obs, comp, prob)
  out.pop('reliability')
  return out


PRIOR_PSEUDO_COUNT = 5  # cells the training scans barely fill lean on their ring's rate


def ring_depth_prior(split, sensor, num: int) -> dict:
  """The same for a table: the training scans' keep rate per (ring, depth
  bin) cell, the cells as the ``ring_depth`` rate term forms them
  (drops.ring_depth_cells). The term's targets are these rates, taken
  from each training batch instead of the whole split."""
  import jax
  from dusty_jax import codec, drops
  from dusty_jax.metrics import ground_truth
  cells_of = jax.jit(lambda x: drops.ring_depth_cells(x, x > codec.ALPHA, sensor))
  def cells(depth):
    return np.concatenate([np.asarray(cells_of(codec.encode(d, sensor)))
                           for d in np.array_split(depth, max(1, len(depth) // 64))])
  train = np.asarray(split('train'))
  keep = np.asarray(codec.valid_depth(train, sensor), np.float64)
  num_cells = train.shape[1] * drops.RATE_DEPTH_BINS
  index = cells(train)
  kept = np.bincount(index.ravel(), keep.ravel(), minlength=num_cells)
  seen = np.bincount(index.ravel(), minlength=num_cells)
  ring_rate = np.repeat(keep.mean(axis=(0, 2)), drops.RATE_DEPTH_BINS)
  rate = (kept + PRIOR_PSEUDO_COUNT * ring_rate) / (seen + PRIOR_PSEUDO_COUNT)
  obs, comp, prob = (np.asarray(split('test', k)[:num]) for k in ('', 'complete', 'drop_prob'))
  out = ground_truth.measurability_scores(sensor, rate[cells(obs)], obs, comp, prob)
  out.pop('reliability')
  return out


def plot(results: dict, real_rate: float, path: str, title: str):
  plt = common.pyplot()
  fig, axes = plt.subplots(1, 3, figsize=(15, 4))
  # One distinct colour per variant (the default cycle repeats after 10).
  colours = plt.get_cmap('tab20')(np.arange(len(results)) % 20)
  for (name, r), colour in zip(results.items(), colours):
    c = r['curves']
    axes[0].plot(c['step'], c['drop_rate'], label=name, lw=1, color=colour)
    axes[1].plot(c['ring_step'], c['ring_corr'], marker='o', ms=3, label=name, color=colour)
    axes[2].plot(c['step'], c['d_real'], lw=1, label=name, color=colour)
    axes[2].plot(c['step'], c['d_fake'], lw=1, ls='--', color=colour)
  axes[0].axhline(real_rate, color='k', ls=':', label='real scans')
  axes[0].set_ylabel('drop rate of generated scans (G, training batch)')
  axes[1].set_ylabel("corr. of EMA's per-ring drop rate with the data's")
  axes[2].set_ylabel('D logits: real (solid), fake (dashed)')
  for ax in axes:
    ax.set_xlabel('training step (batch 16)')
  axes[0].set_yscale('log')
  axes[0].legend(fontsize=7)
  fig.suptitle(title)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def merge(a):
  """Writes one plot and JSON of earlier screens' results (--merge) or of
  run directories' training curves (--runs)."""
  results, sources = {}, []
  for path in [p for p in a.merge.split(',') if p]:
    with open(path) as f:
      r = json.load(f)
    for name, v in r['results'].items():
      steps = v.get('steps', r.get('steps'))  # a merged file keeps each result's
      results[f'{name} ({steps} steps)' if name in results else name] = dict(v, steps=steps)
    sources += r.get('sources') or [dict(file=os.path.basename(path), steps=r['steps'],
                                         machine=r['machine']['banner'])]
  for item in [r for r in a.runs.split(',') if r]:
    name, run = item.split('=', 1)
    c = {k: [] for k in ('step', 'drop_rate', 'real_drop_rate', 'd_real', 'd_fake')}
    with open(os.path.join(run, 'metrics.jsonl')) as f:
      for line in f:
        m = json.loads(line)
        for k in c:
          c[k].append(m[k])
    c.update(ring_step=[], ring_corr=[])
    results[name] = {'curves': c, 'steps': c['step'][-1]}
  real_rate = float(np.mean(next(iter(results.values()))['curves']['real_drop_rate']))
  os.makedirs(a.out, exist_ok=True)
  plot(results, real_rate, os.path.join(a.out, f'{a.name}.png'), a.title)
  common.write_json(os.path.join(a.out, f'{a.name}.json'),
                    dict(sources=sources, results=results))
  for name, r in results.items():
    c = r['curves']
    print(f'{name:28s} {c["step"][-1]:6d} steps: drop rate end {c["drop_rate"][-1]:.4f}, '
          f'min after 500 {min([d for s, d in zip(c["step"], c["drop_rate"]) if s > 500] or [float("nan")]):.4f}')


def stages(a):
  """One plot of the evaluations a run got at several lengths (--stages:
  result JSONs of the same variants at growing --steps): the measurability's
  AUC and ECE, and the depth's completion and fit errors, against the step."""
  runs = {}
  for path in [p for p in a.stages.split(',') if p]:
    with open(path) as f:
      r = json.load(f)
    for name, v in r['results'].items():
      runs.setdefault(name, []).append((r['steps'], v['eval']))
  plt = common.pyplot()
  fig, axes = plt.subplots(1, 2, figsize=(10, 4))
  for name, evs in runs.items():
    evs.sort(key=lambda e: e[0])
    steps = [s for s, _ in evs]
    line, = axes[0].plot(steps, [e['measurability']['auc_near'] for _, e in evs], 'o-',
                         label=f'{name}: AUC <40 m')
    axes[0].plot(steps, [e['measurability']['ece'] for _, e in evs], 's--',
                 color=line.get_color(), label=f'{name}: ECE')
    axes[1].plot(steps, [e['fit']['abs_rel'] for _, e in evs], 'o-', color=line.get_color(),
                 label=f'{name}: fit')
    axes[1].plot(steps, [e['completion']['abs_rel'] for _, e in evs], 's--',
                 color=line.get_color(), label=f'{name}: completion')
  axes[0].set_title('measurability (held-out scans)')
  axes[1].set_title('depth: AbsRel of the inverted x_tilde')
  for ax in axes:
    ax.set_xlabel('training step (batch 16)')
    ax.legend(fontsize=7)
  fig.suptitle(a.title)
  fig.tight_layout()
  os.makedirs(a.out, exist_ok=True)
  fig.savefig(os.path.join(a.out, f'{a.name}.png'), dpi=110)
  common.write_json(os.path.join(a.out, f'{a.name}.json'),
                    {name: [dict(steps=s, **e) for s, e in evs] for name, evs in runs.items()})
  for name, evs in runs.items():
    for s, e in evs:
      print(f'{name:30s} {s:5d} steps: AUC <40 m {e["measurability"]["auc_near"]:.3f}, '
            f'ECE {e["measurability"]["ece"]:.3f}, completion {e["completion"]["abs_rel"]:.3f}, '
            f'fit {e["fit"]["abs_rel"]:.3f}')


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--workdir', default='runs/screen')
  p.add_argument('--out', default=os.path.join(HERE, 'results'))
  p.add_argument('--name', default='drops_screen', help='result file stem')
  p.add_argument('--variants', default=','.join(VARIANTS))
  p.add_argument('--steps', type=int, default=600)
  p.add_argument('--every', type=int, default=100, help='checkpoint interval')
  p.add_argument('--num-invert', type=int, default=16)
  p.add_argument('--invert-steps', type=int, default=200)
  p.add_argument('--train-only', action='store_true')
  p.add_argument('--data-dir', default='', help="prepared scans ('': the study's simulated ones)")
  p.add_argument('--title', default='DUSty-I at the CPU scale: point-drop mechanisms')
  p.add_argument('--merge', default='',
                 help='comma-separated result JSONs of earlier screens: plot and '
                      'write them together (no training)')
  p.add_argument('--runs', default='',
                 help='NAME=RUN_DIR,...: plot the drop-rate curves of these '
                      'training runs (no training; e.g. a run on another machine)')
  p.add_argument('--stages', default='',
                 help='comma-separated result JSONs of the same runs at growing '
                      '--steps: plot their evaluations against the step (no training)')
  a = p.parse_args(argv)
  if a.stages:
    return stages(a)
  if a.merge or a.runs:
    return merge(a)
  from dusty_jax import codec, sensor as sensor_lib, trainer
  from dusty_jax.data import arrays, pipeline
  common.print_banner()
  names = [v for v in a.variants.split(',') if v]
  for v in names:
    if v not in VARIANTS:
      sys.exit(f'error: unknown variant {v!r}; known: {", ".join(VARIANTS)}')
  results, prior, depth_prior = {}, None, None
  for v in names:
    config = config_of(v, a.steps, a.every, a.data_dir)
    workdir = os.path.join(a.workdir, v)
    print(f'== {v}: {dict(VARIANTS[v])} -> {workdir}', flush=True)
    trainer.train_and_evaluate(config, workdir, log=lambda *_: None)
    if a.train_only:
      continue
    sensor = sensor_lib.from_config(config.sensor)
    d = pipeline.dataset_dir(config, sensor, log=lambda *_: None)
    split = lambda s, kind='': arrays.load_split(d, s, sensor, kind)
    train = np.asarray(split('train')[:512])
    real_rings = ring_drop_rate(codec.encode(train, sensor))
    if prior is None:
      prior = ring_prior(split, sensor, a.num_invert, 1 - real_rings)
      print("   reference, each ring's training keep rate as the measurability: "
            f'AUC near {prior["auc_near"]:.3f} surface {prior["auc_surface"]:.3f}, '
            f'ECE {prior["ece"]:.3f}', flush=True)
      depth_prior = ring_depth_prior(split, sensor, a.num_invert)
      print("   reference, each (ring, neighbours' depth) cell's training keep rate: "
            f'AUC near {depth_prior["auc_near"]:.3f} surface {depth_prior["auc_surface"]:.3f}, '
            f'within rings {depth_prior["auc_near_within_ring"]:.3f}, '
            f'ECE {depth_prior["ece"]:.3f}', flush=True)
    # Keyed by the training length too: a run continued to more steps is
    # evaluated again.
    cache = os.path.join(workdir, f'screen_eval_{a.num_invert}_{a.invert_steps}_'
                                  f'step{a.steps}.json')
    ev = json.load(open(cache)) if os.path.isfile(cache) else {}
    if 'auc_near_within_ring' not in ev.get('measurability', {}):  # older caches lack it
      ev = evaluate(workdir, split, a.num_invert, a.invert_steps)
      json.dump(ev, open(cache, 'w'))
    results[v] = {'options': VARIANTS[v], 'eval': ev,
                  'curves': curves(workdir, real_rings)}
    c, m = results[v]['curves'], ev['measurability']
    late = [r for s, r in zip(c['step'], c['drop_rate']) if s > 500]
    print(f'   drop rate end {c["drop_rate"][-1]:.4f} (min after 500: '
          f'{min(late) if late else float("nan"):.4f}; real {c["real_drop_rate"][-1]:.3f}), '
          f'ring corr {c["ring_corr"][-1]:+.2f}, D {c["d_real"][-1]:+.2f}/'
          f'{c["d_fake"][-1]:+.2f}; AUC near {m["auc_near"]:.3f} surface '
          f'{m["auc_surface"]:.3f}, within rings {m["auc_near_within_ring"]:.3f}, '
          f'ECE {m["ece"]:.3f}, completion AbsRel '
          f'{ev["completion"]["abs_rel"]:.3f}, fit {ev["fit"]["abs_rel"]:.3f}', flush=True)
  if results:
    real_rate = float(np.mean(next(iter(results.values()))['curves']['real_drop_rate']))
    os.makedirs(a.out, exist_ok=True)
    plot(results, real_rate, os.path.join(a.out, f'{a.name}.png'), a.title)
    common.write_json(os.path.join(a.out, f'{a.name}.json'),
                      dict(steps=a.steps, num_invert=a.num_invert,
                           invert_steps=a.invert_steps, ring_prior=prior,
                           ring_depth_prior=depth_prior,
                           results=results))


if __name__ == '__main__':
  main()
