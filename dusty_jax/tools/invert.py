"""Reconstructs or restores scans with a trained generator (GAN inversion).

    python -m dusty_jax.tools.invert --workdir RUN --input FILE_OR_DIR \\
        [--corrupt drop:0.9|beams:8|noise:0.01] [--init random|encoder] --out DIR

Inputs: KITTI ``.bin`` files (unfolded with the run's sensor), or ``.npy``
holding metric depth (H, W) or (N, H, W) (the prepared format). Writes per
scan ``NAME_inv_depth.npy`` (complete x_tilde), ``NAME_measurability.npy``,
``NAME_depth.npy`` (the re-rendered scan in metres), ``NAME.ply`` (its
points) and ``NAME.png`` (target, corrupted input, x_tilde, measurability,
re-rendered scan), plus ``metrics.json``.

    python -m dusty_jax.tools.invert --workdir RUN --split test --num 100 [--corrupt ...]
        [--protocol reference|paper]

evaluates over the first --num scans of a prepared split instead and prints
the layout of the paper's Table III (the authors evaluate every test scan).
``--protocol paper`` computes the Chamfer distance as the authors' code
(every pixel of both scans, dropped ones at the origin); the default,
``reference``, over valid points only. metrics.json records the protocol,
N, seeds, the scans taken, the sensor and the dusty_jax version.
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np
from absl import flags

from dusty_jax import tools


def main(argv=None):
  f = flags.FlagValues()
  flags.DEFINE_string('workdir', None, "training run directory (or an authors' .pth)",
                      flag_values=f, required=True)
  flags.DEFINE_string('input', None, '.bin/.npy file or directory', flag_values=f)
  flags.DEFINE_string('split', None, 'evaluate over this prepared split instead',
                      flag_values=f)
  flags.DEFINE_integer('num', 100, 'scans of --split', lower_bound=1, flag_values=f)
  flags.DEFINE_string('corrupt', '', 'drop:F, beams:K or noise:S', flag_values=f)
  flags.DEFINE_string('out', 'inversion', 'output folder', flag_values=f)
  flags.DEFINE_integer('steps', 1000, 'optimisation steps per scan (0: the start '
                       'alone, e.g. the encoder\'s answer)', lower_bound=0, flag_values=f)
  flags.DEFINE_enum('init', 'random', ['random', 'encoder'],
                    "where the search starts: 'random' (the authors') or 'encoder' "
                    '(the run\'s encoder, from python -m dusty_jax.tools.train_encoder)',
                    flag_values=f)
  flags.DEFINE_integer('batch', 16, 'scans inverted together', lower_bound=1,
                       flag_values=f)
  flags.DEFINE_integer('seed', 0, 'random seed', flag_values=f)
  flags.DEFINE_enum('protocol', 'reference', ['reference', 'paper'],
                    "Table III's Chamfer distance: 'reference' over valid points, "
                    "'paper' as the authors (dropped pixels at the origin in both)",
                    flag_values=f)
  tools.parse(f, argv, __doc__)
  tools.run(run, f)


def table_provenance(a, sensor, num: int) -> dict:
  """What metrics.json records of how its numbers were computed."""
  from dusty_jax.metrics import protocol  # as run() does: --help needs no JAX
  points = ('every pixel, dropped ones at the origin' if a.protocol == 'paper'
            else 'every valid pixel')
  rule = (f'the first {a.num} scans of split {a.split!r}' if a.split
          else f'every readable scan of {a.input!r}')
  seeds = {'seed': a.seed, 'batch': a.batch,
           'keys': 'k = fold_in(key(seed), batch start) corrupts the batch; '
                   'fold_in(k, i) starts the search of its scan i'}
  return protocol.provenance(a.protocol, num, points, seeds, rule, sensor)


def run(a):
  import jax
  import tqdm
  import trimesh
  # The library (and JAX) load once the flags are good: --help and a bad flag
  # answer at once.
  from dusty_jax import codec, corrupt, generator, inversion, writers
  from dusty_jax.data import arrays, pipeline, scan_files  # (as above)
  from dusty_jax.metrics import protocol, reconstruction  # (as above)

  if bool(a.input) == bool(a.split):
    raise ValueError('give exactly one of --input and --split')
  if a.corrupt:
    corrupt.parse(a.corrupt)
  params, config = generator.load(a.workdir)
  if a.init == 'encoder':
    from dusty_jax import encoder  # only for this start
    encoder.check_has_encoder(params, a.workdir)
  sensor = params.sensor
  angles = np.asarray(params.angles)
  if a.input:
    items = scan_files.read_scans(a.input, sensor)
  else:
    if config is None:
      raise ValueError(f'{a.workdir}: --split needs a run directory (its config names '
                       'the dataset); give --input scans for a single generator file')
    d = pipeline.dataset_dir(config, sensor, log=lambda m: None)
    data = arrays.load_split(d, a.split, sensor)
    items = [(f'{a.split}_{i:05d}', data[i]) for i in range(min(a.num, len(data)))]
    truth = arrays.load_ground_truth(d, a.split, sensor, len(items))
  os.makedirs(a.out, exist_ok=True)
  key = jax.random.key(a.seed)
  per_scan = []
  measurability, complete_err = [], []
  for start in tqdm.trange(0, len(items), a.batch, desc='inverting', unit='batch',
                           file=sys.stderr):
    chunk = items[start:start + a.batch]
    depth = np.stack([np.nan_to_num(d, nan=0.0, posinf=0.0) for _, d in chunk])
    clean = codec.encode(depth, sensor)
    k = jax.random.fold_in(key, start)
    target = corrupt.apply(a.corrupt, k, clean, sensor) if a.corrupt else clean
    keys = jax.vmap(lambda i: jax.random.fold_in(k, i))(jax.numpy.arange(len(chunk)))
    res = jax.device_get(inversion.invert(params, target, key=keys,
                                          num_steps=a.steps, init=a.init))
    errs = reconstruction.errors(depth, res, angles, sensor, a.protocol)
    if a.split and truth is not None:
      sl = slice(start, start + len(chunk))
      measurability.append(res['measurability'])
      complete_err.append(reconstruction.completion_errors(res, truth[0][sl], sensor))
    for i, (name, _) in enumerate(chunk):
      per_scan.append({'name': name, **{m: float(v[i]) for m, v in errs.items()},
                       'loss': float(res['loss'][i])})
      if a.input:
        np.save(os.path.join(a.out, f'{name}_inv_depth.npy'), res['inv_depth'][i])
        np.save(os.path.join(a.out, f'{name}_measurability.npy'),
                res['measurability'][i])
        np.save(os.path.join(a.out, f'{name}_depth.npy'), res['depth'][i])
        pts = res['points'][i][res['valid'][i]]
        trimesh.PointCloud(pts).export(os.path.join(a.out, f'{name}.ply'))
        tiles = [[writers.inv_depth_tile(clean[i])],
                 [writers.inv_depth_tile(target[i])],
                 [writers.inv_depth_tile(res['inv_depth'][i])],
                 [writers.prob_tile(res['measurability'][i])],
                 [writers.inv_depth_tile(res['scan'][i])]]
        writers.save_grid(os.path.join(a.out, f'{name}.png'), tiles)
  columns = [k for k, _, _ in reconstruction.COLUMNS]
  mean = {k: float(np.nanmean([r[k] for r in per_scan])) for k in columns}
  label = f'{params.model}' + (f' ({a.corrupt})' if a.corrupt else '')
  with open(os.path.join(a.out, 'metrics.json'), 'w') as f:
    json.dump({**table_provenance(a, sensor, len(per_scan)), 'mean': mean,
               'per_scan': per_scan, 'corrupt': a.corrupt, 'steps': a.steps,
               'init': a.init},
              f, indent=2)
  print(f'protocol {a.protocol}: {len(per_scan)} scans')
  print(protocol.format_table({label: mean}, reconstruction.COLUMNS))
  if measurability:
    from dusty_jax.metrics import calibration  # only with ground truth
    comp = {k: float(np.nanmean(np.concatenate([c[k] for c in complete_err])))
            for k in complete_err[0]}
    cal = calibration.reliability(np.concatenate(measurability), 1.0 - truth[1])
    print(protocol.format_table({'x_tilde vs complete depth': comp},
                                reconstruction.COLUMNS))
    print(f'measurability vs true return probability: ECE {cal["ece"]:.4f}')
    writers.line_plot(os.path.join(a.out, 'reliability.png'),
                      {'measured': (np.arange(len(cal['pred'])), cal['truth']),
                       'predicted': (np.arange(len(cal['pred'])), cal['pred'])},
                      'bin of predicted measurability', 'return probability',
                      title=f'ECE {cal["ece"]:.4f}')
    with open(os.path.join(a.out, 'metrics.json')) as f:
      saved = json.load(f)
    saved['ground_truth'] = {'complete_depth': comp, 'ece': cal['ece'],
                             'reliability': {k: np.asarray(v).tolist()
                                             for k, v in cal.items() if k != 'ece'}}
    with open(os.path.join(a.out, 'metrics.json'), 'w') as f:
      json.dump(saved, f, indent=2)


if __name__ == '__main__':
  main()
