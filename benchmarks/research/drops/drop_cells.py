"""Where a generator's own samples drop points: keep rate by ring and depth.

    python benchmarks/research/drops/drop_cells.py [--models sim-dusty1,sim-dusty1-authors,...]
        [--runs NAME=RUN_DIR|NAME=FILE.npz,...] [--num 512]

drop_oracles.py scores measurability through inversion of held-out scans,
which mixes two things: the depth the search recovers and the head. This
looks at the generator alone. It draws ``--num`` scans from each model and
tabulates its mean measurability per (ring, depth bin) cell, the depth bins
(drops.RATE_DEPTH_EDGES) judged on the sample's own complete depth
x_tilde, over its surface pixels. Beside it, the same table of the training
split's observed keep rate on the simulator's complete depth
(drop_oracles.cell_rates). Printed per model:

  * ``corr all``: the correlation of the two tables over the cells nearer
    than 40 m that both fill (at least --min-pixels each): rings and depths;
  * ``corr within rings``: the same after taking each ring's mean out of
    both: does the keep rate move with depth inside a ring as the data's does;
  * ``slope agree``: the share of rings whose keep rate falls (or rises) from
    the near bins to the 30-40 m bin in the same direction as the data's;
  * ``spread``: the standard deviation of the model's table over those cells
    (a model that keeps everything has correlations of noise: read them
    with it).
  * ``near share``: of the surface pixels in the rings where every pixel of
    the data is a surface (no sky, no ego vehicle), the share nearer than
    the first depth edge (5 m): does the generator draw the near objects at
    all (the data's share is printed above the table).

The table of each model and the data's go to a PNG beside the JSON
(``--out``, default benchmarks/research/drops/results/drop_cells.json).
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import numpy as np

# benchmarks/ holds common.py, shared with the product benchmarks.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..'))
import common
import dusty_jax
from drop_oracles import cell_rates, cell_sums
from dusty_jax import codec, configs, drops, sampling
from dusty_jax.data import arrays, pipeline
from dusty_jax.metrics import ground_truth
from dusty_jax.sensor import get_sensor

HERE = os.path.dirname(os.path.abspath(__file__))


def sample_cells(params, sensor, edges, num, batch=64, seed=0):
  """(mean measurability, pixel count), each (H, len(edges) + 1), of ``num``
  samples' surface pixels by ring and bin of their own complete depth."""
  shape = (sensor.height, len(edges) + 1)
  total, count = np.zeros(shape), np.zeros(shape, np.int64)
  key = jax.random.key(seed)
  for i in range(0, num, batch):
    out = sampling.sample(params, jax.random.fold_in(key, i), min(batch, num - i))
    depth = np.asarray(codec.complete_depth(out['inv_depth'], sensor), np.float64)
    sums, n = cell_sums(out['measurability'], depth, sensor, edges)
    total, count = total + sums, count + n
  return np.where(count > 0, total / np.maximum(count, 1), np.nan), count


def agreement(gen, gen_n, real, real_n, near_bins, min_pixels):
  """corr all, corr within rings, slope agree, cells used (see the doc)."""
  use = (gen_n >= min_pixels) & (real_n >= min_pixels)
  use[:, near_bins:] = False
  w = real_n * use

  def corr(a, b):
    a, b = a[use], b[use]
    if len(a) < 3 or a.std() == 0 or b.std() == 0:
      return float('nan')
    return float(np.corrcoef(a, b)[0, 1])

  def centred(t):  # each ring's weighted mean over its used cells taken out
    m = (np.where(use, t, 0) * w).sum(1, keepdims=True) / np.maximum(w.sum(1, keepdims=True), 1)
    return t - m

  last = near_bins - 1  # the 30-40 m bin
  rings = [r for r in range(len(use)) if use[r, last] and use[r, :last].any()]

  def slope(t, r):
    near = np.average(t[r, :last][use[r, :last]], weights=w[r, :last][use[r, :last]])
    return t[r, last] - near

  agree = [np.sign(slope(gen, r)) == np.sign(slope(real, r)) for r in rings]
  return dict(spread=float(gen[use].std()) if use.any() else float('nan'),
              corr_all=corr(gen, real), corr_within_rings=corr(centred(gen), centred(real)),
              slope_agree=float(np.mean(agree)) if agree else float('nan'),
              rings_with_slope=len(rings), cells=int(use.sum()))


def plot(path, tables, edges):
  plt = common.pyplot()
  fig, axes = plt.subplots(1, len(tables), figsize=(2.6 * len(tables), 4.2), sharey=True)
  labels = [f'<{edges[0]:.0f}'] + [f'{a:.0f}-{b:.0f}' for a, b in zip(edges, edges[1:])] + [
      f'>{edges[-1]:.0f}']
  for ax, (name, t) in zip(np.atleast_1d(axes), tables.items()):
    im = ax.imshow(t, aspect='auto', vmin=0, vmax=1, cmap='viridis', interpolation='nearest')
    ax.set_title(name, fontsize=8)
    ax.set_xticks(range(len(labels)), labels, rotation=90, fontsize=6)
    ax.set_xlabel('depth bin (m)', fontsize=7)
  np.atleast_1d(axes)[0].set_ylabel('ring (0 = top)')
  fig.colorbar(im, ax=axes, label='keep rate / mean measurability', shrink=0.8)
  fig.suptitle('keep rate by ring and depth: the data (complete depth) and each '
               "generator's samples (its x_tilde); white: no pixels", fontsize=8)
  fig.savefig(path, dpi=120)
  plt.close(fig)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--models', default='sim-dusty1,sim-dusty1-authors,sim-dusty2',
                 help='load_pretrained names')
  p.add_argument('--runs', default='',
                 help='NAME=RUN_DIR or NAME=FILE.npz,...: trained runs (their EMA), exported generators')
  p.add_argument('--num', type=int, default=512, help='samples per model')
  p.add_argument('--min-pixels', type=int, default=200, help='pixels a cell needs, each side')
  p.add_argument('--out', default=os.path.join(HERE, 'results', 'drop_cells.json'))
  a = p.parse_args(argv)
  try:
    models = {n: dusty_jax.load_pretrained(n) for n in a.models.split(',') if n}
    for item in (i for i in a.runs.split(',') if i):
      if '=' not in item:
        raise ValueError(f'--runs {item!r}: expected NAME=RUN_DIR')
      name, run = item.split('=', 1)
      if run.endswith('.npz'):  # an exported generator (generator.export)
        from dusty_jax import generator
        models[name] = generator.load_file(run)
      else:
        models[name] = dusty_jax.load_checkpoint(run)[0]
  except (OSError, ValueError) as e:
    raise SystemExit(f'error: {e}') from None
  common.print_banner()
  config = configs.study('dusty1')
  sensor = get_sensor(config.sensor.preset)
  d = pipeline.dataset_dir(config, sensor, log=print)
  load = lambda kind='': np.asarray(arrays.load_split(d, 'train', sensor, kind), np.float64)
  edges = np.asarray(drops.RATE_DEPTH_EDGES)
  near_bins = int(np.searchsorted(edges, ground_truth.NEAR_M)) + 1
  obs, comp = load(), load('complete')
  real, real_n = cell_rates(obs, comp, sensor, edges)
  real = np.where(real_n > 0, real, np.nan)
  tables, out = {f'data ({len(obs)} training scans)': real}, {}
  # Rings where every pixel of the data is a surface.
  solid = np.asarray(codec.valid_depth(comp, sensor)).all(axis=(0, 2))
  near_share = lambda n: float(n[solid, 0].sum() / max(n[solid].sum(), 1))
  filled = real_n >= a.min_pixels
  filled[:, near_bins:] = False
  real_spread = float(real[filled].std())
  print(f'{len(obs)} training scans; {a.num} samples per model; cells nearer than '
        f'{ground_truth.NEAR_M:.0f} m with >= {a.min_pixels} pixels each side; the data '
        f"table's spread over its own: {real_spread:.4f}; its near share (rings "
        f"{np.flatnonzero(solid).min()}-{np.flatnonzero(solid).max()}): {near_share(real_n):.4f}")
  print(f'{"model":24s}{"corr all":>10s}{"corr within rings":>19s}{"slope agree":>13s}'
        f'{"cells":>7s}{"mean keep":>11s}{"spread":>9s}{"near share":>12s}')
  for name, params in models.items():
    gen, gen_n = sample_cells(params, sensor, edges, a.num)
    s = agreement(gen, gen_n, real, real_n, near_bins, a.min_pixels)
    s['mean_keep_surface'] = float(np.nansum(gen * gen_n) / gen_n.sum())
    s['near_share'] = near_share(gen_n)
    out[name] = dict(s, table=np.round(gen, 4).tolist(), pixels=gen_n.astype(int).tolist())
    tables[name] = gen
    print(f'{name:24s}{s["corr_all"]:10.3f}{s["corr_within_rings"]:19.3f}'
          f'{s["slope_agree"]:13.2f}{s["cells"]:7d}{s["mean_keep_surface"]:11.3f}'
          f'{s["spread"]:9.4f}{s["near_share"]:12.4f}')
  png = os.path.splitext(a.out)[0] + '.png'
  plot(png, tables, edges)
  common.write_json(a.out, dict(num=a.num, min_pixels=a.min_pixels, near_m=ground_truth.NEAR_M,
                                depth_edges_m=edges.tolist(), data_spread=real_spread,
                                data_near_share=near_share(real_n),
                                data_table=np.round(real, 4).tolist(),
                                data_pixels=real_n.tolist(),
                                models=out))
  print(f'wrote {a.out} and {png}')


if __name__ == '__main__':
  main()
