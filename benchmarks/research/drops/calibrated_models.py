"""Shipped models beside faithful ones calibrated per ring, on one split.

Each model is scored as it is and with its level calibrated per ring after
training (placement_curve.calibrate_rings): drop placement of ``--num``
held-out scans inverted ``--steps`` iterations against the simulator's truth
(AUC < 40 m, within rings, ECE, completion), and Table II of its samples
against the split (JSD, MMD, ... on ``--synthesis`` scans, ``--seeds``
seeds). The question: does "keep the GAN's placement, fix only the level"
beat the shipped models' drop terms?

    python benchmarks/research/drops/calibrated_models.py \
        --models sim-dusty1,sim-dusty2,faithful1=RUN_A,faithful2=RUN_B \
        --data-dir ~/.cache/dusty_jax/synthetic/kitti_64x256_n2000_s0 --split val

A model is a pretrained name, or NAME=WORKDIR (its latest checkpoint).
Writes NAME.json to --out. Choose on --split val; report test.
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

import common  # noqa: E402
import placement_curve  # noqa: E402


def load(item: str):
  from dusty_jax import generator, pretrained
  if '=' in item:
    name, where = item.split('=', 1)
    if where.endswith('.npz'):  # an exported generator (generator.export)
      return name, generator.load_file(where)
    return name, generator.load(where, log=lambda *_: None)[0]
  return item, pretrained.load_pretrained(item)


def synthesis_row(params, depth, num: int, points: int, seeds: int) -> dict:
  from dusty_jax import evaluation
  rec = evaluation.synthesis(params, depth, num=num, points=points, seeds=seeds)
  row = rec['rows'][evaluation.row_label(params, rec['tolerance'])]
  return {k: float(np.mean(v)) for k, v in row.items()}


def picture_rows(params, depth, steps: int):
  """The inverted measurability of each of the scans ``depth``."""
  from dusty_jax import evaluation
  return np.concatenate([res['measurability'] for *_, res in evaluation.restore_batches(
      params, depth, num_steps=steps, batch=len(depth))])


def draw(shown: dict, depth, drop_prob, sensor, path: str):
  """Per scan: the observed scan, the simulator's keep probability, then
  each map's measurability (rows of one figure)."""
  from dusty_jax import codec
  plt = common.pyplot()
  rows = []
  for i in range(len(depth)):
    rows += [(f'scan {i}', np.asarray(codec.encode(depth[i], sensor)), -1),
             (f'scan {i}: the simulator\'s keep probability', 1 - drop_prob[i], 0)]
    rows += [(f'scan {i}: {k}', v[i], 0) for k, v in shown.items()]
  fig, axes = plt.subplots(len(rows), 1, figsize=(8, 1.15 * len(rows)), layout='constrained')
  for ax, (title, image, lo) in zip(axes, rows):
    ax.imshow(image, vmin=lo, vmax=1, cmap='viridis', interpolation='nearest')
    ax.set_title(title, fontsize=8)
    ax.axis('off')
  fig.savefig(path, dpi=90)
  print(f'wrote {path}')


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  p.add_argument('--models', required=True, help='NAME, NAME=WORKDIR or NAME=FILE.npz, comma-separated')
  p.add_argument('--data-dir', required=True, help='the prepared simulated dataset')
  p.add_argument('--split', default='val', choices=('val', 'test'))
  p.add_argument('--num', type=int, default=64, help='held-out scans inverted')
  p.add_argument('--steps', type=int, default=300, help='inversion iterations')
  p.add_argument('--synthesis', type=int, default=200, help='scans per Table II set')
  p.add_argument('--points', type=int, default=512)
  p.add_argument('--seeds', type=int, default=2)
  p.add_argument('--forms', default='as shipped,rings,inverted',
                 help="of each model: 'as shipped', 'without levels', 'rings' (one offset "
                      "per ring, placement_curve.calibrate_rings), 'inverted' (the library's "
                      "drop levels, evaluation.fit_levels: fitted to inversions of "
                      "--fit-scans training scans; the fit to samples that 'levels' and "
                      "'cells' named left the library after 6f82cd7..a7a438e)")
  p.add_argument('--fit-scans', type=int, default=256,
                 help="training scans inverted for the 'inverted' form")
  p.add_argument('--picture', type=int, default=0,
                 help='also draw the measurability of this many scans (NAME.png)')
  p.add_argument('--out', default=os.path.join(HERE, 'results'))
  p.add_argument('--name', default='calibrated_models')
  a = p.parse_args(argv)
  from dusty_jax import evaluation, levels
  from dusty_jax.data import arrays
  from dusty_jax.metrics import ground_truth
  from dusty_jax.sensor import get_sensor
  with open(os.path.join(a.data_dir, 'meta.json')) as f:
    sensor = get_sensor(json.load(f)['sensor'])
  split = np.asarray(arrays.load_split(a.data_dir, a.split, sensor))
  depth, complete, prob = (np.asarray(arrays.load_split(a.data_dir, a.split, sensor, k)
                                      [:max(a.num, a.picture)])
                           for k in ('', 'complete', 'drop_prob'))
  ring_keep = evaluation.training_ring_keep(a.data_dir, sensor)
  if a.num:
    depth, complete, prob, shown_depth = depth[:a.num], complete[:a.num], prob[:a.num], depth
    table = ground_truth.ring_table_scores(sensor, ring_keep, depth, complete, prob)
    table.pop('reliability')
    print(f'per-ring table: AUC<40 {table["auc_near"]:.3f} within '
          f'{table["auc_near_within_ring"]:.3f}', flush=True)
  else:
    shown_depth = depth
  train = np.asarray(arrays.load_split(a.data_dir, 'train', sensor)[:evaluation.RING_TABLE_SCANS])
  make = {'as shipped': lambda p: p,
          'without levels': levels.without_levels,
          'rings': lambda p: placement_curve.calibrate_rings(p, ring_keep),
          'inverted': lambda p: evaluation.fit_levels(p, train, num=a.fit_scans,
                                                      num_steps=a.steps, progress=True)}
  results, shown = {}, {}
  for item in [m for m in a.models.split(',') if m]:
    name, params = load(item)
    for form in a.forms.split(','):
      model = make[form](params)
      if a.picture:
        shown[f'{name} ({form})'] = picture_rows(model, shown_depth[:a.picture], a.steps)
      if not a.num:
        continue
      r = placement_curve.score(model, depth, (complete, prob), ring_keep, a.steps)
      r['synthesis'] = synthesis_row(model, split, a.synthesis, a.points, a.seeds)
      r['sample_drop_rate'] = placement_curve.sample_drop_rate(model)
      results[f'{name} ({form})'] = r
      m, s = r['placement'], r['synthesis']
      print(f'{name} ({form}): AUC<40 {m["auc_near"]:.3f} within '
            f'{m["auc_near_within_ring"]:.3f} ECE {m["ece"]:.3f} completion '
            f'{r["completion_abs_rel"]:.3f} | drop {r["sample_drop_rate"]:.3f} JSD x1e2 '
            f'{100 * s["jsd"]:.1f} MMD x1e3 {1e3 * s["mmd"]:.2f} 1-NNA '
            f'{100 * s["1nna"]:.1f} COV {100 * s["cov"]:.1f}', flush=True)
  if shown:
    os.makedirs(a.out, exist_ok=True)
    truth = np.asarray(arrays.load_split(a.data_dir, a.split, sensor, 'drop_prob')[:a.picture])
    draw(shown, shown_depth[:a.picture], truth, sensor,
         os.path.join(a.out, f'{a.name}.png'))
  if not a.num:
    return
  record = {'machine': common.machine(), 'split': a.split, 'num': a.num, 'steps': a.steps,
            'synthesis': {'num': a.synthesis, 'points': a.points, 'seeds': a.seeds},
            'ring_table': table, 'real_drop_rate': float(np.mean(split == 0)),
            'models': results}
  os.makedirs(a.out, exist_ok=True)
  with open(os.path.join(a.out, f'{a.name}.json'), 'w') as f:
    json.dump(record, f, indent=1)
  print(f'wrote {a.out}/{a.name}.json')


if __name__ == '__main__':
  main()
