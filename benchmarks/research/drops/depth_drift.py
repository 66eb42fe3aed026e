"""Does a run keep its scene's range? The depth drift of point-drop variants.

    python benchmarks/research/drops/depth_drift.py --runs NAME=RUN_DIR,... [--pretrained NAME,...]
        [--num 32] [--every 500] [--out benchmarks/research/drops/results --name depth_drift]
        [--samples NAME]

Variants that hold their drops can lose their depth: the inverted x_tilde
of held-out scans lies far behind the surfaces (README.md here, "Depth
that survives the drops"). For each run this reports
  * over training, ``depth_gap`` from its metrics.jsonl (runs trained while
    the metric existed, up to f597033): the mean over rings of |mean returned value of the
    generated scans - the real batch's|, in normalised inverse depth;
  * at each kept checkpoint (train with ``--config.keep_every=500`` to keep
    them all), on ``--num`` held-out simulated test scans
    inverted by that checkpoint's EMA generator: the fit and completion
    AbsRel, the measurability's AUC on surfaces nearer than 40 m, the
    median complete depth of the bottom eight rings (the ground) of 64
    sampled x_tilde against the real scans' returns there, and their
    speckle: the share of x_tilde pixels farther than both ring neighbours
    by more than DIP in normalised inverse depth (isolated far pixels, a
    checkerboard at its worst; the simulator's complete scans have almost
    none), and their peaks, the same nearer than both neighbours.
``--pretrained`` scores shipped generators the same way, beside the runs.
Evaluations are cached in the result JSON: a rerun only adds what is new.
Writes ``NAME.json``, ``NAME.png`` and ``NAME_samples.png`` (one sample of
each run's last checkpoint and of each shipped generator) to ``--out``.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys

import numpy as np

# benchmarks/ holds common.py, shared with the product benchmarks.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..'))
import common
import drops_screen
from dusty_jax.drops import DIP  # the dip_weight term's threshold

HERE = os.path.dirname(os.path.abspath(__file__))
GROUND_RINGS = 8  # the bottom rings: near ground in every simulated scene


def speckle(x, valid=None, peaks: bool = False) -> float:
  """Share of pixels of ``x`` (B, H, W) below both ring neighbours by more
  than DIP (``peaks``: above both); with ``valid``, of the valid pixels with
  valid neighbours."""
  left, right = np.roll(x, 1, -1), np.roll(x, -1, -1)
  if peaks:
    dips = x > np.maximum(left, right) + DIP
  else:
    dips = x < np.minimum(left, right) - DIP
  if valid is None:
    return float(dips.mean())
  both = valid & np.roll(valid, 1, -1) & np.roll(valid, -1, -1)
  return float(dips[both].mean())


def gap_curve(workdir: str) -> dict:
  steps, gaps = [], []
  if not os.path.exists(os.path.join(workdir, 'metrics.jsonl')):
    return {'step': steps, 'depth_gap': gaps}
  with open(os.path.join(workdir, 'metrics.jsonl')) as f:
    for line in f:
      m = json.loads(line)
      if 'depth_gap' in m:
        steps.append(m['step'])
        gaps.append(m['depth_gap'])
  return {'step': steps, 'depth_gap': gaps}


def samples(params, num: int = 64) -> dict:
  """Of ``num`` x_tilde sampled by ``params``: the median complete depth (m)
  of the bottom rings, the speckle, and the peaks (the same, nearer than
  both neighbours: what the dip term leaves unpaid)."""
  import jax
  from dusty_jax import codec, sampling
  x = np.asarray(sampling.sample(params, jax.random.key(7), num)['inv_depth'])
  depth = np.asarray(codec.complete_depth(x, params.sensor))
  return {'ground_depth_m': float(np.median(depth[:, -GROUND_RINGS:])), 'speckle': speckle(x),
          'peaks': speckle(x, peaks=True)}


def picture(generators: dict, path: str):
  """One sampled x_tilde per generator ({label: params}), its left quarter
  enlarged: the speckle is single pixels."""
  import jax
  from dusty_jax import sampling
  plt = common.pyplot()
  fig, axes = plt.subplots(len(generators), 2, figsize=(16, 2.1 * len(generators)),
                           gridspec_kw=dict(width_ratios=(4, 1)), squeeze=False)
  for (label, params), (full, crop) in zip(generators.items(), axes):
    x = np.asarray(sampling.sample(params, jax.random.key(7), 1)['inv_depth'])[0]
    for ax, img in ((full, x), (crop, x[-32:, :64])):
      ax.imshow(img, cmap='turbo', vmin=-1, vmax=1, interpolation='nearest', aspect='auto')
      ax.set_xticks([])
      ax.set_yticks([])
    full.set_ylabel(label, fontsize=8)
    full.set_title(f'x_tilde (speckle {speckle(x[None]):.3f})', fontsize=8)
    crop.set_title('bottom-left 32 x 64, enlarged', fontsize=8)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def plot(results: dict, shipped: dict, real: dict, path: str):
  plt = common.pyplot()
  fig, axes = plt.subplots(2, 2, figsize=(15, 9))
  axes = axes.ravel()
  last = max([int(s) for r in results.values() for s in r['checkpoints']] or [0])
  for (name, e), colour in zip(shipped.items(), ('k', '0.55', 'tab:brown', 'tab:olive')):
    point = dict(marker='*', ms=12, ls='none', color=colour)
    axes[1].plot([last], [e['fit']['abs_rel']], label=f'{name} (shipped): fit', **point)
    axes[1].plot([last], [e['completion']['abs_rel']], color=colour, marker='P',
                 ms=10, ls='none', label=f'{name} (shipped): completion')
    axes[2].plot([last], [e['ground_depth_m']], label=name, **point)
    axes[3].plot([last], [e['speckle']], label=name, **point)
  for name, r in results.items():
    line, = axes[0].plot(r['curve']['step'], r['curve']['depth_gap'], lw=1, label=name)
    ev = sorted(r['checkpoints'].items(), key=lambda kv: int(kv[0]))
    steps = [int(s) for s, _ in ev]
    axes[1].plot(steps, [e['fit']['abs_rel'] for _, e in ev], 'o-', color=line.get_color(),
                 label=f'{name}: fit')
    axes[1].plot(steps, [e['completion']['abs_rel'] for _, e in ev], 's--',
                 color=line.get_color(), label=f'{name}: completion')
    axes[2].plot(steps, [e['ground_depth_m'] for _, e in ev], 'o-', color=line.get_color(),
                 label=name)
    axes[3].plot(steps, [e['speckle'] for _, e in ev], 'o-', color=line.get_color(), label=name)
  axes[2].axhline(real['ground_m'], color='k', ls=':', label='real returns')
  axes[3].axhline(real['speckle'], color='k', ls=':', label='complete simulated scans')
  axes[0].set_ylabel('depth_gap (normalised inverse depth)')
  axes[1].set_ylabel('AbsRel of the inverted x_tilde (held-out scans)')
  axes[2].set_ylabel(f'median depth of the bottom {GROUND_RINGS} rings (m)')
  axes[3].set_ylabel(f'speckle of x_tilde (share of dips > {DIP})')
  for i, ax in enumerate(axes):
    ax.set_xlabel('training step (batch 16)')
    ax.legend(fontsize=7, ncol=2 if i == 1 else 1)
  fig.suptitle('Depth drift of point-drop variants (CPU study scale)')
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--runs', default='', help='NAME=RUN_DIR,...')
  p.add_argument('--num', type=int, default=32, help='held-out scans inverted')
  p.add_argument('--invert-steps', type=int, default=100)
  p.add_argument('--pretrained', default='',
                 help='shipped generators to score beside the runs: NAME,... '
                      '(drawn as stars at the right edge)')
  p.add_argument('--every', type=int, default=500, help='evaluate checkpoints at multiples of')
  p.add_argument('--out', default=os.path.join(HERE, 'results'))
  p.add_argument('--name', default='depth_drift')
  p.add_argument('--samples', default='',
                 help="the samples picture's name (default NAME_samples): it shows the "
                      'runs and shipped generators of this call only')
  a = p.parse_args(argv)
  import dusty_jax
  from dusty_jax import checkpoint, codec, configs, generator, sensor as sensor_lib
  from dusty_jax.data import arrays, pipeline
  common.print_banner()
  path = os.path.join(a.out, f'{a.name}.json')
  cached = json.load(open(path)) if os.path.exists(path) else {}
  old, old_shipped = cached.get('results', {}), cached.get('shipped', {})
  config = configs.study('dusty1')
  sensor = sensor_lib.from_config(config.sensor)
  d = pipeline.dataset_dir(config, sensor, log=print)
  # Every checkpoint's evaluation reads the same test arrays: load each once.
  split = functools.cache(lambda s, kind='': np.asarray(arrays.load_split(d, s, sensor, kind)))
  test = split('test')
  complete = split('test', 'complete')[:64]
  x, valid = (np.asarray(f(complete, sensor)) for f in (codec.encode, codec.valid_depth))
  real = {'ground_m': float(np.median(test[:, -GROUND_RINGS:][
              np.asarray(codec.valid_depth(test[:, -GROUND_RINGS:], sensor))])),
          'speckle': speckle(x, valid), 'peaks': speckle(x, valid, peaks=True)}
  results = {}
  for item in [r for r in a.runs.split(',') if r]:
    name, run = item.split('=', 1)
    done = old.get(name, {}).get('checkpoints', {})
    r = {'run': run, 'curve': gap_curve(run), 'checkpoints': {}}
    for s in sorted(checkpoint.manager(run, keep=1000).all_steps()):
      if s == 0 or s % a.every:
        continue
      e = done.get(str(s))
      if e is None or e.get('num') != a.num or 'speckle' not in e:
        params, _ = generator.load(run, step=s, log=lambda *_: None)
        e = drops_screen.evaluate(run, split, a.num, a.invert_steps, params=params)
        e.update(num=a.num, **samples(params))
      elif 'peaks' not in e:  # scored before peaks were: only the samples again
        e.update(samples(generator.load(run, step=s, log=lambda *_: None)[0]))
      r['checkpoints'][str(s)] = e
      print(f'{name:24s} step {s:5d}: fit {e["fit"]["abs_rel"]:.3f}, completion '
            f'{e["completion"]["abs_rel"]:.3f}, AUC <40 m {e["measurability"]["auc_near"]:.3f}, '
            f'ground {e["ground_depth_m"]:.1f} m (real {real["ground_m"]:.1f}), speckle '
            f'{e["speckle"]:.3f} (real {real["speckle"]:.4f}), peaks {e["peaks"]:.3f} '
            f'(real {real["peaks"]:.4f})', flush=True)
    results[name] = r
  shipped = {}
  for name in [n for n in a.pretrained.split(',') if n]:
    e = old_shipped.get(name)
    if e is None or e.get('num') != a.num:
      params = dusty_jax.load_pretrained(name)
      e = drops_screen.evaluate('', split, a.num, a.invert_steps, params=params)
      e.update(num=a.num, **samples(params))
    elif 'peaks' not in e:
      e.update(samples(dusty_jax.load_pretrained(name)))
    shipped[name] = e
    print(f'{name:24s} shipped   : fit {e["fit"]["abs_rel"]:.3f}, completion '
          f'{e["completion"]["abs_rel"]:.3f}, AUC <40 m {e["measurability"]["auc_near"]:.3f}, '
          f'ground {e["ground_depth_m"]:.1f} m, speckle {e["speckle"]:.3f}, '
          f'peaks {e["peaks"]:.3f}', flush=True)
  os.makedirs(a.out, exist_ok=True)
  common.write_json(path, dict(results=dict(old, **results), shipped=dict(old_shipped, **shipped),
                               real=real, num=a.num, invert_steps=a.invert_steps))
  plot(dict(old, **results), dict(old_shipped, **shipped), real,
       os.path.join(a.out, f'{a.name}.png'))
  last = {f'{name}, step {max(r["checkpoints"], key=int)}':
          generator.load(r['run'], step=int(max(r['checkpoints'], key=int)),
                         log=lambda *_: None)[0]
          for name, r in results.items() if r['checkpoints']}
  last.update({f'{name} (shipped)': dusty_jax.load_pretrained(name) for name in shipped})
  if last:
    picture(last, os.path.join(a.out, f'{a.samples or a.name + "_samples"}.png'))


if __name__ == '__main__':
  main()
