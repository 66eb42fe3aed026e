"""Reconstructs or restores scans with a trained generator (GAN inversion).

    python -m dusty_jax.invert --workdir RUN --input FILE_OR_DIR \
        [--corrupt drop:0.9|beams:8|noise:0.01] --out DIR

Inputs: KITTI ``.bin`` files (unfolded with the run's sensor), or ``.npy``
holding metric depth (H, W) or (N, H, W) (the prepared format). Writes per
scan ``NAME_inv_depth.npy`` (complete x_tilde), ``NAME_measurability.npy``,
``NAME_depth.npy`` (the re-rendered scan in metres), ``NAME.ply`` (its
points) and ``NAME.png`` (target, corrupted input, x_tilde, measurability,
re-rendered scan), plus ``metrics.json``.

    python -m dusty_jax.invert --workdir RUN --split test --num 100 [--corrupt ...]
        [--protocol reference|paper]

evaluates over the first --num scans of a prepared split instead and prints
the layout of the paper's Table III (the authors evaluate every test scan).
``--protocol paper`` computes the Chamfer distance as the authors' code
(every pixel of both scans, dropped ones at the origin); the default,
``reference``, over valid points only. metrics.json records the protocol,
N, seeds, the scans taken, the sensor and the dusty_jax version.

This module is also callable: ``dusty_jax.invert(params, scan)`` runs
:func:`dusty_jax.inversion.invert` whichever of the two the name refers to.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import types

import numpy as np

from dusty_jax import inversion


class _CallableModule(types.ModuleType):
  def __call__(self, *args, **kwargs):
    return inversion.invert(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule

TABLE_COLUMNS = (('cd', 'CD x1e4', 1e4), ('abs_rel', 'AbsRel', 1),
                 ('sq_rel', 'SqRel', 1), ('rmse', 'RMSE', 1),
                 ('rmse_log', 'RMSElog', 1), ('delta1', 'd<1.25 %', 100),
                 ('delta2', 'd<1.25^2 %', 100), ('delta3', 'd<1.25^3 %', 100))


def read_inputs(path: str, sensor, log=print):
  """[(name, metric depth (H, W))] from a file or a directory of files.

  A file that cannot be read is reported and skipped (and counted by the
  caller), as prepare does; only a run with no readable file fails.
  """
  from dusty_jax.data import kitti
  if os.path.isdir(path):
    files = sorted(os.path.join(path, f) for f in os.listdir(path)
                   if f.endswith(('.bin', '.npy')))
    if not files:
      raise FileNotFoundError(f'{path}: no .bin or .npy files')
  elif os.path.isfile(path):
    files = [path]
  else:
    raise FileNotFoundError(f'{path}: no such file or directory')
  out, skipped = [], []
  for f in files:
    stem = os.path.splitext(os.path.basename(f))[0]
    try:
      if f.endswith('.bin'):
        depth, _ = kitti.load_scan(f, sensor)
        out.append((stem, depth))
        continue
      arr = np.load(f, allow_pickle=False)
      if arr.shape[-2:] != sensor.shape or arr.ndim not in (2, 3):
        raise ValueError(f'{f}: expected metric depth of shape (H, W) or '
                         f'(N, H, W) with H, W = {sensor.shape}, got {arr.shape}')
    except (ValueError, OSError) as e:
      skipped.append((f, str(e)))
      log(f'skipped: {e}')
      continue
    if arr.ndim == 2:
      out.append((stem, arr))
    else:
      out += [(f'{stem}_{i:05d}', a) for i, a in enumerate(arr)]
  if not out:
    raise ValueError(f'{path}: none of {len(files)} input files could be read')
  if skipped:
    log(f'{len(skipped)} of {len(files)} input files skipped')
  return out


def evaluate_batch(params, target_depth, result, angles, protocol='reference'):
  """Depth errors of x_tilde and Chamfer distance, per scan (numpy dicts).

  x_tilde is complete: every pixel has a range, ALPHA being max_depth, not a
  drop. The Chamfer distance is between the target's and the re-rendered
  scan's points (units of max_depth): ``protocol='reference'`` over their
  valid points only; ``'paper'`` as the authors' code, over all H x W
  pixels of both with every dropped pixel at the origin.
  """
  import jax.numpy as jnp
  from dusty_jax import codec
  from dusty_jax.metrics import chamfer, clouds, depth as depth_metrics
  paper = clouds.check_protocol(protocol) == 'paper'
  sensor = params.sensor
  target_depth = np.asarray(target_depth, np.float32)
  valid_t = np.asarray(codec.valid_depth(target_depth, sensor))
  pred = codec.complete_depth(result['inv_depth'], sensor)
  errs = {k: np.asarray(v) for k, v in
          depth_metrics.depth_errors(pred, target_depth, valid_t).items()}
  pts_t = np.asarray(codec.to_points(np.where(valid_t, target_depth, 0.0),
                                          angles)) / sensor.max_depth
  pts_r = np.asarray(result['points']) / sensor.max_depth
  valid_r = np.asarray(result['valid'])
  cds = []
  for i in range(len(target_depth)):
    if paper:  # fixed size: one compiled shape, no (P, Q) matrix
      a = pts_t[i].reshape(1, -1, 3)
      b = np.where(valid_r[i][..., None], pts_r[i], 0.0).reshape(1, -1, 3)
      cds.append(float(chamfer.pairwise(a, b, tile=1)[0, 0]))
      continue
    a, b = pts_t[i][valid_t[i]], pts_r[i][valid_r[i]]
    cds.append(float(chamfer.chamfer(jnp.asarray(a), jnp.asarray(b)))
               if len(a) and len(b) else float('nan'))
  errs['cd'] = np.array(cds)
  return errs


def ground_truth(directory, split, sensor, num):
  """(complete depth, drop probability) of a simulated split, else None."""
  from dusty_jax.data import arrays
  try:
    return (np.asarray(arrays.load_split(directory, split, sensor, 'complete')[:num]),
            np.asarray(arrays.load_split(directory, split, sensor, 'drop_prob')[:num]))
  except FileNotFoundError:
    return None


def complete_depth_errors(params, result, complete):
  """Errors of x_tilde against the simulator's complete depth (every pixel a
  perfect sensor returns, dropped or not)."""
  from dusty_jax import codec
  from dusty_jax.metrics import depth as depth_metrics
  pred = codec.complete_depth(result['inv_depth'], params.sensor)
  mask = np.asarray(codec.valid_depth(complete, params.sensor))
  out = depth_metrics.depth_errors(pred, complete, mask)
  out = {k: np.asarray(v) for k, v in out.items() if k != 'count'}
  out['cd'] = np.full(len(complete), np.nan)
  return out


def table_provenance(a, sensor, num: int) -> dict:
  """What metrics.json records of how its numbers were computed."""
  from dusty_jax.metrics import protocol
  points = ('every pixel, dropped ones at the origin' if a.protocol == 'paper'
            else 'every valid pixel')
  rule = (f'the first {a.num} scans of split {a.split!r}' if a.split
          else f'every readable scan of {a.input!r}')
  seeds = {'seed': a.seed, 'batch': a.batch,
           'keys': 'k = fold_in(key(seed), batch start) corrupts the batch; '
                   'fold_in(k, i) starts the search of its scan i'}
  return protocol.provenance(a.protocol, num, points, seeds, rule, sensor)


def format_table(rows: dict) -> str:
  """Rows {label: {metric: mean}} in the layout of the paper's Table III."""
  head = f'{"":24s}' + ''.join(f'{name:>12s}' for _, name, _ in TABLE_COLUMNS)
  lines = [head, '-' * len(head)]
  for label, m in rows.items():
    lines.append(f'{label:24s}' + ''.join(
        f'{m[k] * s:12.3f}' for k, _, s in TABLE_COLUMNS))
  return '\n'.join(lines)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--workdir', required=True, help='training run directory')
  p.add_argument('--input', help='.bin/.npy file or directory')
  p.add_argument('--split', help='evaluate over this prepared split instead')
  p.add_argument('--num', type=int, default=100, help='scans of --split')
  p.add_argument('--corrupt', default='', help='drop:F, beams:K or noise:S')
  p.add_argument('--out', default='inversion')
  p.add_argument('--steps', type=int, default=1000)
  p.add_argument('--batch', type=int, default=16)
  p.add_argument('--seed', type=int, default=0)
  p.add_argument('--protocol', choices=('reference', 'paper'), default='reference',
                 help="Table III's Chamfer distance: 'reference' over valid points, "
                 "'paper' as the authors (dropped pixels at the origin in both)")
  a = p.parse_args(argv)
  try:
    run(a)
  except (ValueError, FileNotFoundError) as e:
    sys.exit(f'error: {e}')


def run(a):
  import jax
  import tqdm
  import trimesh
  from dusty_jax import checkpoint, codec, corrupt, writers
  from dusty_jax.data import arrays, pipeline

  if bool(a.input) == bool(a.split):
    raise ValueError('give exactly one of --input and --split')
  if a.corrupt:
    corrupt.parse(a.corrupt)
  params, config = checkpoint.load_checkpoint(a.workdir)
  sensor = params.sensor
  angles = np.asarray(params.angles)
  if a.input:
    items = read_inputs(a.input, sensor)
  else:
    d = pipeline.dataset_dir(config, sensor, log=lambda m: None)
    data = arrays.load_split(d, a.split, sensor)
    items = [(f'{a.split}_{i:05d}', data[i]) for i in range(min(a.num, len(data)))]
    truth = ground_truth(d, a.split, sensor, len(items))
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
                                          num_steps=a.steps))
    errs = evaluate_batch(params, depth, res, angles, a.protocol)
    if a.split and truth is not None:
      sl = slice(start, start + len(chunk))
      measurability.append(res['measurability'])
      complete_err.append(complete_depth_errors(params, res, truth[0][sl]))
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
  columns = [k for k, _, _ in TABLE_COLUMNS]
  mean = {k: float(np.nanmean([r[k] for r in per_scan])) for k in columns}
  label = f'{config.model}' + (f' ({a.corrupt})' if a.corrupt else '')
  with open(os.path.join(a.out, 'metrics.json'), 'w') as f:
    json.dump({**table_provenance(a, sensor, len(per_scan)), 'mean': mean,
               'per_scan': per_scan, 'corrupt': a.corrupt, 'steps': a.steps},
              f, indent=2)
  print(f'protocol {a.protocol}: {len(per_scan)} scans')
  print(format_table({label: mean}))
  if measurability:
    from dusty_jax.metrics import calibration
    comp = {k: float(np.nanmean(np.concatenate([c[k] for c in complete_err])))
            for k in complete_err[0]}
    cal = calibration.reliability(np.concatenate(measurability), 1.0 - truth[1])
    print(format_table({'x_tilde vs complete depth': comp}))
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
