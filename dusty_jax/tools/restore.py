"""Restores damaged or sparse scans: fills their missing pixels.

    python -m dusty_jax.tools.restore --workdir sim-dusty1 --input FILE_OR_DIR \\
        [--corrupt beams:4|drop:0.9] [--methods auto,linear] [--source vlp16] --out DIR

RUN (--workdir) is a training run directory, a pretrained model's name, a
generator ``.npz`` or an authors' ``.pth``: its sensor decides the grid.

Inputs: KITTI ``.bin`` files (unfolded with the model's sensor, or with
--source), or ``.npy`` metric depth (H, W) or (N, H, W). Which pixels are
missing:
  * ``--corrupt beams:4`` (or ``drop:0.9``): the input is whole; the tool
    removes pixels, restores them and scores each method against the input
    (the removed returns: AbsRel, MAE, on depth edges, Chamfer), beside
    linear interpolation;
  * ``--source vlp16`` (a preset or a spec .json): the input is a sparser
    sensor's scan; its beams are placed on the model's grid by elevation
    (restoration.on_grid) and every other row restored;
  * neither: the input's pixels without a return are filled.

Writes per scan and method ``NAME_METHOD_depth.npy`` (metres, every pixel)
and ``NAME_METHOD.ply``, a picture ``NAME.png`` (the input, each method's
result and, with --corrupt, its error on the removed returns) and, with
--corrupt, ``metrics.json``.
"""

from __future__ import annotations

import json
import os

import numpy as np
from absl import flags

from dusty_jax import tools

METHODS = ('nearest', 'linear', 'morphological', 'learned', 'inversion', 'auto')  # restoration.METHODS


def main(argv=None):
  f = flags.FlagValues()
  flags.DEFINE_string('workdir', None, tools.model_help('the generator'),
                      flag_values=f, required=True)
  flags.DEFINE_string('input', None, '.bin/.npy file or directory', flag_values=f,
                      required=True)
  flags.DEFINE_string('corrupt', '', 'drop:F or beams:K: remove pixels of a whole '
                      'input and score the restorations against it', flag_values=f)
  flags.DEFINE_string('source', None, "the input's sensor where it is not the model's "
                      '(a preset name or a spec .json): its beams are placed on the '
                      "model's grid", flag_values=f)
  flags.DEFINE_list('methods', ['auto'], f'comma-separated, of {", ".join(METHODS)}',
                    flag_values=f)
  flags.DEFINE_integer('steps', 300, "'inversion''s iterations", lower_bound=0,
                       flag_values=f)
  flags.DEFINE_string('out', 'restored', 'output folder', flag_values=f)
  flags.register_validator('methods', lambda ms: ms and set(ms) <= set(METHODS),
                           f'--methods: each one of {", ".join(METHODS)}', flag_values=f)
  flags.register_validator('corrupt', lambda s: tools.valid_corruption(s, removing=True),
                           flag_values=f)
  flags.register_multi_flags_validator(
      ['corrupt', 'source'], lambda v: not (v['corrupt'] and v['source']),
      'give at most one of --corrupt (a whole input) and --source (a sparser sensor)',
      flag_values=f)
  tools.parse(f, argv, __doc__)
  tools.run(run, f)


def inputs(a, params):
  """(names, depth (N, H, W), known (N, H, W)) on the model's grid."""
  from dusty_jax import evaluation, restoration, sensor as sensor_lib  # as run()
  from dusty_jax.data import scan_files  # (as above)
  sensor = params.sensor
  if a.source:
    source = (sensor_lib.load(a.source) if a.source.endswith('.json')
              else sensor_lib.get_sensor(a.source)).with_width(sensor.width)
    items = scan_files.read_scans(a.input, source)
    depth, known = restoration.on_grid(np.stack([d for _, d in items]), source, sensor)
  else:
    items = scan_files.read_scans(a.input, sensor)
    depth = np.stack([d for _, d in items])
    known = (evaluation.corruption_known(a.corrupt, len(depth), sensor.shape)
             if a.corrupt else depth > 0)
  return [n for n, _ in items], depth, known


def picture(path, name, given, results, target, sensor):
  """The input, each method's result and, with a target, the relative
  error on the removed returns."""
  import matplotlib
  matplotlib.use('Agg')
  import matplotlib.pyplot as plt
  rows = [('input', given, None)]
  for method, depth in results.items():
    err = None
    if target is not None:
      err = np.where(target['mask'], np.abs(depth - target['depth']) /
                     np.maximum(target['depth'], 1e-6), np.nan)
      method = f'{method}: AbsRel {np.nanmean(err):.3f} on the removed returns'
    rows.append((method, depth, err))
  if target is not None:
    rows.insert(0, ('target (the whole input)', target['depth'], None))
  fig, axes = plt.subplots(len(rows), 2 if target is not None else 1, squeeze=False,
                           figsize=(13 if target is not None else 7, 1.3 * len(rows)),
                           layout='constrained')
  norm = matplotlib.colors.LogNorm(sensor.min_depth + 1, sensor.max_depth)
  im_e = None
  for (title, depth, err), ax in zip(rows, axes):
    im_d = ax[0].imshow(np.where(depth > 0, depth, np.nan), cmap='turbo_r', norm=norm,
                        interpolation='nearest', aspect='auto')
    ax[0].set_title(title, fontsize=8)
    if err is not None:
      im_e = ax[1].imshow(err, cmap='magma', vmin=0, vmax=0.3, interpolation='nearest',
                          aspect='auto')
      ax[1].set_title('|error| / range on the removed returns', fontsize=8)
    for x in ax:
      x.set_xticks([])
      x.set_yticks([])
    if err is None and len(ax) > 1:
      ax[1].axis('off')
  fig.colorbar(im_d, ax=axes[:, 0], label='range (m); white: no return', shrink=0.6)
  if im_e is not None:
    fig.colorbar(im_e, ax=axes[:, 1], label='relative error', shrink=0.6)
  fig.suptitle(name, fontsize=9)
  fig.savefig(path, dpi=90)
  plt.close(fig)


def run(a):
  # The library (and JAX) load once the flags are good.
  import trimesh
  from dusty_jax import codec, restoration  # (as above)
  from dusty_jax.metrics import records, restoration as fill_metrics  # (as above)

  if os.path.exists(a.out) and not os.path.isdir(a.out):
    raise ValueError(f'--out={a.out}: a file, not a folder; give a folder for the results')
  params, _ = tools.load_model(a.workdir)
  sensor = params.sensor
  names, depth, known = inputs(a, params)
  methods = list(dict.fromkeys(a.methods))
  if a.corrupt and 'linear' not in methods:
    methods.append('linear')  # every score stands beside interpolation's
  os.makedirs(a.out, exist_ok=True)
  scores = {m: [] for m in methods}
  for i, name in enumerate(names):
    given = np.where(known[i], depth[i], 0.0)
    results = {}
    for m in methods:
      out = restoration.restore(params, given, known[i], method=m, num_steps=a.steps)
      label = m if m != 'auto' else f'auto ({out["method"]})'
      results[label] = out['depth']
      stem = os.path.join(a.out, f'{name}_{m}')
      np.save(stem + '_depth.npy', out['depth'])
      trimesh.PointCloud(np.asarray(codec.to_points(out['depth'], params.angles)).reshape(
          -1, 3)).export(stem + '.ply')
      if a.corrupt:
        s = fill_metrics.scores(out['depth'][None], depth[i][None], known[i][None],
                                params.angles, sensor)
        scores[m].append({k: float(v[0]) for k, v in s.items()})
    target = None
    if a.corrupt:
      target = {'depth': depth[i], 'mask': np.asarray(codec.valid_depth(depth[i], sensor))
                & ~known[i]}
    picture(os.path.join(a.out, f'{name}.png'), name, given, results, target, sensor)
    print(f'{name}: ' + ', '.join(f'{m}' for m in results), flush=True)
  if a.corrupt:
    mean = {m: {k: records.finite_mean([s[k] for s in v]) for k in fill_metrics.NAMES}
            for m, v in scores.items()}
    with open(os.path.join(a.out, 'metrics.json'), 'w') as f:
      json.dump({'corrupt': a.corrupt, 'num': len(names), 'scored': 'the removed returns',
                 'mean': mean, 'per_scan': scores}, f, indent=2)
    print(f'{"method":14} {"AbsRel":>7} {"x linear":>8} {"edge AbsRel":>11} {"MAE m":>6} '
          f'{"CD x1e4":>7}')
    lin = mean['linear']['abs_rel']
    for m, v in mean.items():
      print(f'{m:14} {v["abs_rel"]:7.4f} {v["abs_rel"] / lin:8.2f} '
            f'{v["edge_abs_rel"]:11.4f} {v["mae"]:6.3f} {1e4 * v["cd"]:7.2f}')
  print(f'written to {a.out}')


if __name__ == '__main__':
  main()
