"""Restoration: every method against every corruption, error against time.

    python benchmarks/restore.py [--model sim-dusty1] [--split test] [--num 32]
        [--methods nearest,linear,morphological,learned,inversion] [--out benchmarks/results]

Corrupts held-out simulated HDL-64E scans (the main command's cached data,
split --split) and, where ../shared/data/kitti-sample holds them, the real
KITTI scans (64 x 256 as the authors subsample them), then fills the removed
pixels with each method of ``dusty_jax.restore``: the classical baselines,
the learned fill (restorer.py) and the paper's GAN inversion (300 iterations). Scores the
removed returns (evaluation.fill: AbsRel, MAE, the same on depth edges,
Chamfer) and times one scan at a time (median; the call that compiles not
counted). Writes restore.json and restore.png (AbsRel against seconds per
scan), restore_kitti.png (a real scan's beams:4 restored by each) and
restore_vlp16.png (a real VLP-16 sweep upsampled to the HDL-64E grid); with
--cross_sensor N, N simulated scene pairs upsampled from a VLP-16 to the
HDL-64E; and linear interpolation scored as the README's other restoration
figures are (beside_table3).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

import common

HERE = os.path.dirname(os.path.abspath(__file__))
CORRUPTIONS = ('beams:2', 'beams:4', 'beams:8', 'drop:0.5', 'drop:0.9')
METHODS = ('nearest', 'linear', 'morphological', 'learned', 'inversion')
KITTI_SAMPLE = os.path.join(HERE, '..', '..', 'shared', 'data', 'kitti-sample')


def parse_args(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--model', default='sim-dusty1')
  p.add_argument('--split', default='test', choices=['val', 'test'])
  p.add_argument('--num', type=int, default=32, help='simulated scans')
  p.add_argument('--inversion_num', type=int, default=8,
                 help='of those, how many inversion restores (1-2 s each)')
  p.add_argument('--methods', default=','.join(METHODS))
  p.add_argument('--corruptions', default=','.join(CORRUPTIONS))
  p.add_argument('--cross_sensor', type=int, default=16,
                 help='simulated scene pairs, VLP-16 upsampled to HDL-64E (0: none)')
  p.add_argument('--out', default=os.path.join(HERE, 'results'))
  p.add_argument('--replot', action='store_true',
                 help="redraw the pictures from --out's restore.json; measure nothing")
  return p.parse_args(argv)


def datasets(params, split: str, num: int):
  """{name: (N, H, W) metres}: simulated scans and the KITTI sample."""
  from experiments import synthetic
  from dusty_jax.data import arrays, kitti, pipeline
  d = pipeline.dataset_dir(synthetic.get_config(), params.sensor)
  out = {f'simulated {split}': np.asarray(arrays.load_split(d, split, params.sensor)[:num])}
  files = sorted(f for f in os.listdir(KITTI_SAMPLE) if f.endswith('.bin')) if (
      os.path.isdir(KITTI_SAMPLE)) else []
  if files:
    out['real KITTI'] = np.stack([kitti.load_scan(os.path.join(KITTI_SAMPLE, f),
                                                  params.sensor)[0] for f in files])
  return out


def cross_sensor(params, methods, num: int, first_seed: int = 50_000) -> list[dict]:
  """Upsampling a sparser sensor: the same simulated scenes (seeds the
  training never used) rendered by a VLP-16 and by the model's HDL-64E; the
  VLP-16's beams placed on the HDL-64E grid (restoration.on_grid: 9 of its
  16 beams lie in the HDL-64E's field of view) and the other rows restored,
  scored against the HDL-64E scan on every row the VLP-16 did not give."""
  import time
  from dusty_jax import restoration, sensor as sensor_lib
  from dusty_jax.data import simulated_lidar
  from dusty_jax.metrics import records, restoration as fill_metrics
  target = params.sensor
  source = sensor_lib.get_sensor('vlp16').with_width(target.width)
  seeds = range(first_seed, first_seed + num)
  sparse = np.stack([simulated_lidar.render_scan(s, source).depth for s in seeds])
  dense = np.stack([simulated_lidar.render_scan(s, target).depth for s in seeds])
  depth, known = restoration.on_grid(sparse, source, target)
  out = []
  for m in methods:
    n = min(num, 8) if m == 'inversion' else num
    restoration.restore(params, depth[0], known[0], method=m)  # compiles: not timed
    filled, seconds = [], []
    for i in range(n):
      t = time.perf_counter()
      filled.append(restoration.restore(params, depth[i], known[i], method=m)['depth'])
      seconds.append(time.perf_counter() - t)
    sc = fill_metrics.scores(np.stack(filled), dense[:n], known[:n], params.angles, target)
    out.append({'method': m, 'corrupt': 'vlp16 to hdl64e', 'num': n,
                'mean': {k: records.finite_mean(v) for k, v in sc.items()},
                'seconds_per_scan': float(np.median(seconds)), 'data': 'simulated pairs'})
  return out


def beside_table3(num: int = 64, seed: int = 7) -> dict:
  """Linear interpolation scored as the README's other restoration figures
  are (benchmarks/study.py, scaling.py: the first ``num`` test scans,
  corruptions drawn with ``seed``, AbsRel against the clean scan over all its
  returns): the baseline beside each of them. noise:0.01 has no pixel to
  fill: its figure is the noisy scan's own."""
  import jax
  if os.path.join(HERE, '..') not in sys.path:  # experiments/, for study.py's call too
    sys.path.insert(0, os.path.join(HERE, '..'))
  from experiments import synthetic
  from dusty_jax import codec, corrupt, evaluation, interpolation, sensor as sensor_lib
  from dusty_jax.data import arrays, pipeline
  from dusty_jax.metrics import restoration as fill_metrics
  out = {}
  for preset in ('kitti', 'vlp16'):
    config = synthetic.get_config()
    if preset == 'vlp16':
      config.sensor.preset, config.sensor.width = 'vlp16', 256
    sensor = sensor_lib.from_config(config.sensor)
    d = pipeline.dataset_dir(config, sensor)
    depth = np.asarray(arrays.load_split(d, 'test', sensor)[:num])
    angles = arrays.load_angles(d, sensor)
    row = {}
    for spec in ('drop:0.9', 'beams:4'):
      known = evaluation.corruption_known(spec, len(depth), sensor.shape, seed)
      filled = np.stack([interpolation.linear(np.where(k, x, 0.0), k, sensor.min_depth,
                                              sensor.max_depth)
                         for x, k in zip(depth, known)])
      s = fill_metrics.scores(np.where(known & (depth > 0), depth, filled), depth, known,
                              angles, sensor)
      row[spec] = float(np.nanmean(s['scan_abs_rel']))
    k_corrupt = jax.random.split(jax.random.key(seed))[0]
    noisy = [np.asarray(codec.decode(corrupt.apply('noise:0.01', jax.random.fold_in(
        k_corrupt, i), codec.encode(x, sensor), sensor), sensor)[0])
             for i, x in enumerate(depth)]
    valid = np.asarray(codec.valid_depth(depth, sensor))
    row['noise:0.01 (the noisy scan)'] = float(np.mean(
        [np.mean(np.abs(n[v] - x[v]) / x[v]) for n, x, v in zip(noisy, depth, valid)]))
    out[preset] = {'num': len(depth), 'seed': seed, 'abs_rel_vs_clean_scan': row}
    print(f'beside Table III ({preset}, {len(depth)} test scans, seed {seed}): linear '
          + ', '.join(f'{k} {v:.4f}' for k, v in row.items()), flush=True)
  return out


def plot(results, path):
  """AbsRel (dots; crosses: on edges) against seconds per scan, a panel
  per data and corruption, a colour per method."""
  plt = common.pyplot()
  panels = list(dict.fromkeys((r['data'], r['corrupt']) for r in results))
  cols = min(len(panels), 5)
  rows = -(-len(panels) // cols)
  fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3 * rows), squeeze=False,
                           layout='constrained')
  colours = dict(zip(METHODS, plt.cm.tab10.colors))
  for ax in axes.ravel()[len(panels):]:
    ax.axis('off')
  for ax, (name, spec) in zip(axes.ravel(), panels):
    for r in results:
      if (r['data'], r['corrupt']) == (name, spec):
        ax.scatter(r['seconds_per_scan'], r['mean']['abs_rel'], color=colours[r['method']],
                   label=r['method'], s=30)
        ax.scatter(r['seconds_per_scan'], r['mean']['edge_abs_rel'], marker='x',
                   color=colours[r['method']], s=30)
    ax.set_xscale('log')
    ax.set_yscale('log')
    ax.set_title(f'{name}: {spec}', fontsize=9)
    ax.set_xlabel('seconds per scan (log)', fontsize=8)
    ax.set_ylabel('AbsRel, removed returns (x: edges)', fontsize=8)
  axes[0, 0].legend(fontsize=7)
  fig.suptitle('Restoration: error against time per scan (lower left is better)', fontsize=10)
  fig.savefig(path, dpi=90)


def kitti_picture(params, depth, methods, path):
  """One real scan with 3 of 4 beams removed, restored by each method, with
  the error on the removed returns (the restore tool's picture)."""
  from dusty_jax import codec, evaluation, restoration
  from dusty_jax.tools import restore as restore_tool
  sensor = params.sensor
  known = evaluation.corruption_known('beams:4', 1, sensor.shape)[0]
  given = np.where(known, depth, 0.0)
  results = {m: restoration.restore(params, given, known, method=m)['depth'] for m in methods}
  target = {'depth': depth, 'mask': np.asarray(codec.valid_depth(depth, sensor)) & ~known}
  restore_tool.picture(path, 'a real KITTI scan, 3 of 4 beams removed (beams:4)', given,
                       results, target, sensor)


def vlp16_picture(params, methods, path):
  """The real VLP-16 sweep of ../shared/data/sensors-sample placed on the
  model's HDL-64E grid by elevation and restored by each method (the
  restore tool's picture)."""
  from dusty_jax import restoration, sensor as sensor_lib
  from dusty_jax.data import read_points
  from dusty_jax.tools import restore as restore_tool
  sample = os.path.join(os.path.dirname(KITTI_SAMPLE), 'sensors-sample', 'vlp16_ring.pcd')
  if not os.path.isfile(sample):
    return
  target = params.sensor
  source = sensor_lib.get_sensor('vlp16').with_width(target.width)
  pts = read_points(sample)
  depth, known = restoration.points_on_grid(pts, source, target, ring=pts['ring'])
  results = {m: restoration.restore(params, depth, known, method=m)['depth'] for m in methods}
  restore_tool.picture(path, 'a real VLP-16 sweep on the HDL-64E grid (9 of its 16 beams in '
                       'view), restored', depth, results, None, target)


def main(argv=None):
  a = parse_args(argv)
  sys.path.insert(0, os.path.join(HERE, '..'))
  common.print_banner()
  import dusty_jax
  from dusty_jax import evaluation
  params = dusty_jax.load_pretrained(a.model) if a.model in dusty_jax.pretrained.available() \
      else dusty_jax.load_checkpoint(a.model)[0]
  if a.replot:
    with open(os.path.join(a.out, 'restore.json')) as f:
      record = json.load(f)
    return pictures(params, record['results'], a.methods.split(','), a.out)
  methods, specs = a.methods.split(','), a.corruptions.split(',')
  methods = ['linear'] + [m for m in methods if m != 'linear']  # the baseline first
  data = datasets(params, a.split, a.num)
  results = []
  print(f'{"data":16} {"corruption":10} {"method":14} {"AbsRel":>7} {"x linear":>8} '
        f'{"edges":>7} {"x linear":>8} {"MAE m":>6} {"CD x1e4":>7} {"s/scan":>8}')
  for name, depth in data.items():
    for spec in specs:
      rows = {}
      for m in methods:
        n = a.inversion_num if m == 'inversion' else len(depth)
        r = evaluation.fill(params, depth[:n], corruption=spec, method=m)
        r['data'] = name
        results.append(r)
        rows[m] = r
        # linear on the same scans as this method (inversion takes fewer)
        ref = rows.get('linear')
        if ref is not None and n != ref['num']:
          ref = evaluation.fill(params, depth[:n], corruption=spec, method='linear')
        ratio = lambda k: (r['mean'][k] / ref['mean'][k] if ref else float('nan'))
        print(f'{name:16} {spec:10} {m:14} {r["mean"]["abs_rel"]:7.4f} '
              f'{ratio("abs_rel"):8.2f} {r["mean"]["edge_abs_rel"]:7.4f} '
              f'{ratio("edge_abs_rel"):8.2f} {r["mean"]["mae"]:6.2f} '
              f'{1e4 * r["mean"]["cd"]:7.2f} {r["seconds_per_scan"]:8.4f}', flush=True)
        if ref is not None:
          r['vs_linear'] = {k: ratio(k) for k in ('abs_rel', 'edge_abs_rel', 'mae', 'cd')}
          r['linear_on_same_scans'] = ref['mean']
  if a.cross_sensor:
    for r in cross_sensor(params, methods, a.cross_sensor):
      results.append(r)
      print(f'{r["data"]:16} {r["corrupt"]:10} {r["method"]:14} {r["mean"]["abs_rel"]:7.4f} '
            f'{"":8} {r["mean"]["edge_abs_rel"]:7.4f} {"":8} {r["mean"]["mae"]:6.2f} '
            f'{1e4 * r["mean"]["cd"]:7.2f} {r["seconds_per_scan"]:8.4f}', flush=True)
  table3 = beside_table3()
  os.makedirs(a.out, exist_ok=True)
  common.write_json(os.path.join(a.out, 'restore.json'),
                    {'model': a.model, 'split': a.split,
                     'results': [{k: v for k, v in r.items() if k != 'per_scan'}
                                 for r in results],
                     'linear_beside_table3': table3})
  pictures(params, results, methods, a.out)


def pictures(params, results, methods, out):
  plot(results, os.path.join(out, 'restore.png'))
  vlp16_picture(params, [m for m in methods if m != 'inversion'],
                os.path.join(out, 'restore_vlp16.png'))
  if os.path.isdir(KITTI_SAMPLE):
    depth = datasets(params, 'test', 0)['real KITTI'][0]
    kitti_picture(params, depth, methods, os.path.join(out, 'restore_kitti.png'))


if __name__ == '__main__':
  main()
