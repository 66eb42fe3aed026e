"""Evaluation as library code: the paper's Table II (synthesis) and Table
III (restoration by GAN inversion) of a trained generator.

The tools call :func:`synthesis` (and :func:`tune_tolerance` for the
baseline's beta) and :func:`restoration`, as benchmarks do, so that two
reports of one metric cannot differ by a subset rule, a seed or a
training-set row. The test subset follows the protocol
(metrics/protocol.py: ``subset``); the generated set of seed s is sampled
with ``key(SAMPLE_SEED + s)``. Restoration draws per scan
(:data:`RESTORE_KEYS`), so its numbers do not depend on the batch size.
"""

from __future__ import annotations

import json
import os
import sys

import jax
import numpy as np
import tqdm

import time

from dusty_jax import codec, corrupt, inversion, levels, restoration as restoration_lib, sampling, writers
from dusty_jax.data import arrays
from dusty_jax.generator import GeneratorParams
from dusty_jax.metrics import (calibration, ground_truth, protocol, reconstruction, records,
                               restoration as fill_metrics)

SAMPLE_SEED = 1000  # generated set s is sampled with key(SAMPLE_SEED + s).
TRAINING_ROW = 'training set'  # the label of the train vs test row
RING_TABLE_SCANS = 1024  # training scans the per-ring keep-rate table counts
LEVEL_SCANS, LEVEL_STEPS = 256, 300  # training scans fit_levels inverts, and how far
AFTER_TRAINING = 'final_evaluation'  # after_training's files in the run directory
RESTORE_KEYS = ('k_corrupt, k_search = split(key(seed)); scan i of the set is '
                'corrupted with fold_in(k_corrupt, i) and its search starts from '
                'fold_in(k_search, i), whatever the batch')


def encoded_subset(depth, num: int, protocol_name: str, sensor) -> np.ndarray:
  """The protocol's subset of ``num`` scans of a split of metric depth
  (N, H, W), encoded as normalised inverse depth."""
  idx = protocol.subset(len(depth), num, protocol_name)
  return np.asarray(codec.encode(depth[idx], sensor))


def row_label(params: GeneratorParams, tolerance: float) -> str:
  """The generator's row in the result record: the model, and beta if set."""
  return f'{params.model}' + (f' (beta={tolerance:.4f})' if tolerance else '')


def tune_tolerance(params: GeneratorParams, val, *, num: int, trials: int,
                   protocol_name: str = 'reference', points: int = 512) -> float:
  """The baseline's drop tolerance beta, tuned on the protocol's subset of
  ``num`` validation scans (metric depth) against as many samples drawn
  with key 0 (protocol.tune_tolerance)."""
  if params.variant.has_measurability:
    raise ValueError(f'tuning the tolerance is for a model without a measurability; '
                     f'{params.model} needs none')
  val = encoded_subset(val, num, protocol_name, params.sensor)
  gen = sampling.sample_scans(params, jax.random.key(0), len(val))
  return protocol.tune_tolerance(val, gen, params.angles, params.sensor, trials,
                                 points=points, protocol=protocol_name)


def synthesis(params: GeneratorParams, test, train=None, *, num: int = 5000,
              points: int = 2048, seeds: int = 5, protocol_name: str = 'reference',
              tolerance: float | None = None, progress: bool = False) -> dict:
  """Table II of a generator: its samples against a test split, per seed.

  Args:
    params: a trained generator.
    test, train: metric depth (N, H, W) of the test split and, for the
      training-set row (train vs test), of the train split (None: no row).
    num: scans per set; the protocol's subset of the test split may hold
      fewer, and then each set has that many (the record's ``num``).
    points: points per cloud; seeds: generated sets.
    protocol_name: 'reference' or 'paper' (metrics/protocol.py).
    tolerance: beta applied to the samples (None: the generator's).

  Returns:
    The result record (what evaluation.json holds): the provenance
    (protocol, N, points, seeds, subset rule, sensor, version), the
    ``tolerance`` used and ``rows``: {label: {metric: [value per seed]}},
    the generator's row (:func:`row_label`) and the ``TRAINING_ROW``.
  """
  sensor = params.sensor
  ref = encoded_subset(test, num, protocol_name, sensor)
  n = len(ref)
  if n < 2:  # 1-NNA leaves one cloud out: each set needs another
    raise ValueError(f'Table II needs at least 2 scans per set; num={num} of a test split '
                     f'of {len(test)} gives {n}')
  tol = params.tolerance if tolerance is None else float(tolerance)
  cache = {}
  compare = lambda fake, seed, beta=0.0: protocol.compare(
      ref, fake, params.angles, sensor=sensor, protocol=protocol_name,
      num_points=points, seed=seed, tolerance=beta, cache=cache, progress=progress)
  results = {k: [] for k, _, _ in protocol.ROW_SCALES}
  for seed in tqdm.trange(seeds, desc='seeds', file=sys.stderr, disable=not progress):
    m = compare(sampling.sample_scans(params, jax.random.key(SAMPLE_SEED + seed), n),
                seed, tol)
    for k in results:
      results[k].append(m[k])
  rows = {row_label(params, tol): results}
  if train is not None:
    # The authors subsample the training split by the same rule and num.
    num_train = num if protocol_name == 'paper' else n
    m = compare(encoded_subset(train, num_train, protocol_name, sensor)[:n], 0)
    rows[TRAINING_ROW] = {k: [v] for k, v in m.items()}
  provenance_seeds = {'metric': list(range(seeds)),
                      'generator': [SAMPLE_SEED + s for s in range(seeds)],
                      'training_row_metric': 0}
  return {**records.provenance(protocol_name, n, points, provenance_seeds,
                                protocol.SUBSET_RULES[protocol_name], sensor),
          'tolerance': tol, 'rows': rows}


def restore_batches(params: GeneratorParams, depth, *, corruption: str = '',
                    num_steps: int = 1000, init='random', batch: int = 16,
                    seed: int = 0, progress: bool = False, desc: str = 'inverting'):
  """Restores scans of metric depth by GAN inversion, a batch at a time.

  Args:
    params: a trained generator.
    depth: (N, H, W) metres, 0 (or NaN, inf) where there is no return; any
      sequence of scans that slices (a memory-mapped split is read a batch
      at a time).
    corruption: a corrupt.py spec (``drop:0.9``, ``beams:8``,
      ``noise:0.01``) applied to the encoded scans first; '' for none.
    num_steps, init: of ``inversion.invert``.
    batch: scans inverted together (the results do not depend on it).
    seed: the draws of corruption and search (:data:`RESTORE_KEYS`).

  Yields:
    (start, depth, clean, target, result) per batch: the index of its first
    scan, its metric depth (NaN and inf as 0), the encoded scans, the
    corrupted ones and ``invert``'s result (numpy).
  """
  if corruption:
    corrupt.parse(corruption)
  if batch < 1:
    raise ValueError(f'batch={batch!r}: must be a whole number >= 1')
  sensor = params.sensor
  k_corrupt, k_search = jax.random.split(jax.random.key(seed))
  draws = lambda k, idx: jax.vmap(lambda i: jax.random.fold_in(k, i))(idx)
  corrupt_one = lambda k, scan: corrupt.apply(corruption, k, scan, sensor)
  for start in tqdm.trange(0, len(depth), batch, desc=desc, unit='batch',
                           file=sys.stderr, disable=not progress):
    d = np.nan_to_num(np.asarray(depth[start:start + batch], np.float32),
                      nan=0.0, posinf=0.0, neginf=0.0)
    idx = np.arange(start, start + len(d))
    clean = np.asarray(codec.encode(d, sensor))
    target = (np.asarray(jax.vmap(corrupt_one)(draws(k_corrupt, idx), clean))
              if corruption else clean)
    res = jax.device_get(inversion.invert(params, target, key=draws(k_search, idx),
                                          num_steps=num_steps, init=init))
    yield start, d, clean, target, res


def corruption_known(corruption: str, num: int, shape, seed: int = 0) -> np.ndarray:
  """(num, H, W) bool: the pixels ``corruption`` keeps of scans 0..num-1,
  drawn as :func:`restore_batches` draws them (RESTORE_KEYS)."""
  k_corrupt = jax.random.split(jax.random.key(seed))[0]
  return np.stack([np.asarray(corrupt.kept(corruption, jax.random.fold_in(k_corrupt, i),
                                           tuple(shape)))
                   for i in range(num)]) if num else np.zeros((0,) + tuple(shape), bool)


def fill(params: GeneratorParams, depth, *, corruption: str, method: str, seed: int = 0,
         num_steps: int = restoration_lib.INVERSION_STEPS, progress: bool = False) -> dict:
  """How ``restoration.restore(method)`` fills what ``corruption`` (one that
  removes pixels: drop, beams) removes from scans of metric ``depth``
  (N, H, W): metrics.restoration's scores per scan on the removed returns,
  and the wall seconds per scan (one scan at a time; the first call, which
  compiles, is repeated and not counted)."""
  if not corrupt.removes(corruption):
    raise ValueError(f'corruption {corruption!r} removes no pixel: nothing to fill')
  depth = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
  known = corruption_known(corruption, len(depth), params.sensor.shape, seed)
  k_search = jax.random.split(jax.random.key(seed))[1]
  run = lambda i: restoration_lib.restore(
      params, np.where(known[i], depth[i], 0.0), known[i], method=method,
      key=jax.random.fold_in(k_search, i), num_steps=num_steps)
  if len(depth):
    run(0)  # compiles (inversion): not timed
  filled, seconds = [], []
  for i in tqdm.trange(len(depth), desc=f'{method} {corruption}', file=sys.stderr,
                       disable=not progress):
    t = time.perf_counter()
    filled.append(run(i)['depth'])
    seconds.append(time.perf_counter() - t)
  scores = fill_metrics.scores(np.stack(filled), depth, known, params.angles, params.sensor)
  return {'method': method, 'corrupt': corruption, 'num': len(depth), 'seed': seed,
          'steps': num_steps if method == 'inversion' else None,
          'mean': {k: records.finite_mean(v) for k, v in scores.items()},
          'seconds_per_scan': float(np.median(seconds)) if seconds else None,
          'per_scan': [{k: float(v[i]) for k, v in scores.items()}
                       for i in range(len(depth))]}


def fit_levels(params: GeneratorParams, depth, *, num: int = LEVEL_SCANS,
               num_steps: int = LEVEL_STEPS, batch: int = 64, progress: bool = False):
  """``params`` with drop levels per (ring, depth) cell (levels.calibrate)
  fitted to the first ``num`` scans of ``depth`` (metric depth: the
  training split), each inverted ``num_steps`` iterations from a random
  start (:func:`restore_batches`, seed 0). 256 scans x 300 iterations take
  about 4 minutes for the CPU-scale DUSty-I on a 2-core CPU."""
  depth = depth[:num]
  if not len(depth):
    raise ValueError('fit_levels: no training scans to fit drop levels to')
  scans, latents = [], []
  for _, d, _, _, res in restore_batches(params, depth, num_steps=num_steps, batch=batch,
                                         progress=progress, desc='fitting drop levels'):
    scans.append(d)
    latents.append(res['latent'])
  return levels.calibrate(params, np.concatenate(scans), np.concatenate(latents))


def restoration(params: GeneratorParams, depth, *, corruption: str = '',
                num_steps: int = 1000, init='random', batch: int = 16, seed: int = 0,
                protocol_name: str = 'reference', names=None, truth=None,
                subset: str = 'every scan given', each=None,
                progress: bool = False, ring_keep=None) -> dict:
  """Table III of a generator: scans restored by GAN inversion, scored
  against the scans before corruption.

  Args:
    params, depth, corruption, num_steps, init, batch, seed: as
      :func:`restore_batches`.
    protocol_name: the Chamfer distance's: 'reference' over valid points,
      'paper' as the authors (every pixel, dropped ones at the origin).
    names: a name per scan for the record (default its index).
    truth: (complete depth, drop probability) of the same scans, which only
      a simulator has; adds ``ground_truth``: x_tilde's errors against the
      complete depth, the measurability's calibration, and ``placement``:
      how its measurability ranks the scans' own drops
      (metrics.ground_truth.measurability_scores: AUC on surfaces nearer
      than 40 m, the AUC within rings there, ECE).
    ring_keep: with ``truth``, the training split's keep rate per ring
      (metrics.ground_truth.ring_keep_rate): adds ``ring_table``, the same
      scores of that table, which a measurability should beat.
    subset: how the scans were chosen, for the record.
    each: called as ``each(start, clean, target, result)`` per batch (the
      invert tool writes its files there).

  Returns:
    The result record (what the tool's metrics.json holds): the provenance,
    ``mean`` (a column's mean over the scans where it is finite; None where
    none is), ``per_scan`` (name, the columns, final loss), ``corrupt``,
    ``steps``, ``init`` and, with ``truth``, ``ground_truth``.
  """
  sensor = params.sensor
  angles = np.asarray(params.angles)
  names = list(range(len(depth))) if names is None else list(names)
  if len(names) != len(depth):
    raise ValueError(f'{len(names)} names for {len(depth)} scans')
  per_scan, measurability, complete, observed = [], [], [], []
  fills = corrupt.removes(corruption) if corruption else False
  filled_by_inversion = []  # x_tilde (metres), where a corruption removed pixels
  for start, d, clean, target, res in restore_batches(
      params, depth, corruption=corruption, num_steps=num_steps, init=init,
      batch=batch, seed=seed, progress=progress):
    errs = reconstruction.errors(d, res, angles, sensor, protocol_name)
    for i in range(len(d)):
      per_scan.append({'name': names[start + i],
                       **{k: float(v[i]) for k, v in errs.items()},
                       'loss': float(res['loss'][i])})
    if truth is not None:
      sl = slice(start, start + len(d))
      measurability.append(res['measurability'])
      observed.append(d)
      complete.append(reconstruction.completion_errors(res, truth[0][sl], sensor))
    if fills:
      filled_by_inversion.append(np.asarray(codec.complete_depth(res['inv_depth'], sensor)))
    if each is not None:
      each(start, clean, target, res)
  columns = [k for k, _, _ in reconstruction.COLUMNS]
  points = ('every pixel, dropped ones at the origin' if protocol_name == 'paper'
            else 'every valid pixel')
  seeds = {'seed': seed, 'batch': batch, 'keys': RESTORE_KEYS}
  record = {**records.provenance(protocol_name, len(per_scan), points, seeds, subset,
                                  sensor),
            'mean': {k: records.finite_mean([r[k] for r in per_scan]) for k in columns},
            'per_scan': per_scan, 'corrupt': corruption, 'steps': num_steps,
            'init': init if isinstance(init, str) else 'given latents'}
  if fills and per_scan:
    record['fill'] = fill_record(params, depth, corruption, seed, filled_by_inversion)
  if truth is not None and per_scan:
    record['ground_truth'] = _ground_truth_record(
        sensor, truth, np.concatenate(measurability), np.concatenate(observed), complete,
        ring_keep)
  return record


def _ground_truth_record(sensor, truth, measurability, observed, complete,
                         ring_keep=None) -> dict:
  """What :func:`restoration` reports against a simulator's ``truth``
  (complete depth, drop probability) of the scans restored: x_tilde's
  errors against the complete depth (``complete``: per batch,
  reconstruction.completion_errors), how the ``measurability`` (N, H, W)
  is calibrated and ranks the ``observed`` scans' drops, and, with
  ``ring_keep``, the same scores of the training split's per-ring table."""
  comp, prob = (np.asarray(t[:len(observed)]) for t in truth)
  cal = calibration.reliability(measurability, 1.0 - prob)
  brief = lambda scores: {k: scores[k] for k in PLACEMENT}
  record = {
      'complete_depth': {k: records.finite_mean(np.concatenate([c[k] for c in complete]))
                         for k in complete[0]},
      'ece': cal['ece'],
      'placement': brief(ground_truth.measurability_scores(sensor, measurability, observed,
                                                           comp, prob)),
      'reliability': {k: np.asarray(v).tolist() for k, v in cal.items() if k != 'ece'}}
  if ring_keep is not None:
    record['ring_table'] = brief(
        ground_truth.ring_table_scores(sensor, ring_keep, observed, comp, prob))
  return record


def fill_record(params: GeneratorParams, depth, corruption: str, seed: int,
                filled_by_inversion) -> dict:
  """What :func:`restoration` reports where a corruption removed pixels:
  x_tilde's scores on the removed returns (metrics.restoration) beside
  linear interpolation's of the same pixels (:func:`fill`), the baseline
  every restoration figure shows."""
  filled = np.concatenate(filled_by_inversion)
  d = np.nan_to_num(np.asarray(depth[:len(filled)], np.float32), nan=0.0, posinf=0.0,
                    neginf=0.0)
  known = corruption_known(corruption, len(d), params.sensor.shape, seed)
  inverted = fill_metrics.scores(filled, d, known, params.angles, params.sensor)
  linear = fill(params, d, corruption=corruption, method='linear', seed=seed)
  return {'scored': 'the removed pixels that had a return (metrics/restoration.py)',
          'inversion': {k: records.finite_mean(v) for k, v in inverted.items()},
          'linear': linear['mean'],
          'linear_seconds_per_scan': linear['seconds_per_scan']}


def fill_lines(fill_rec: dict) -> list[str]:
  """The lines that show a restoration beside linear interpolation."""
  lines = [f'{"on the removed returns":46} {"AbsRel":>7} {"MAE m":>7} {"edge AbsRel":>11} '
           f'{"edge MAE":>8} {"CD x1e4":>8}']
  for name in ('inversion', 'linear'):
    m = fill_rec[name]
    num = lambda k, scale=1: f'{scale * m[k]:.4f}' if m[k] is not None else 'n/a'
    label = 'GAN inversion (x_tilde)' if name == 'inversion' else 'linear interpolation'
    lines.append(f'  {label:44} {num("abs_rel"):>7} {num("mae"):>7} {num("edge_abs_rel"):>11} '
                 f'{num("edge_mae"):>8} {num("cd", 1e4):>8}')
  inv, lin = fill_rec['inversion']['abs_rel'], fill_rec['linear']['abs_rel']
  if inv is not None and lin:
    lines.append(f'  inversion / linear AbsRel: x{inv / lin:.2f}')
  return lines


# What ``restoration`` reports of drop placement (ground_truth.measurability_scores).
PLACEMENT = ('auc_near', 'auc_near_within_ring', 'auc_surface', 'ece', 'ece_near')


def after_training(params: GeneratorParams, data_dir: str, out: str, *,
                   num_synthesis: int = 200, points: int = 512, num_invert: int = 32,
                   invert_steps: int = 300, picture_scans: int = 4,
                   progress: bool = True) -> dict:
  """A short evaluation of a freshly trained generator on its dataset's test
  split: Table II on ``num_synthesis`` scans (one seed) and, where the data
  is simulated, ``num_invert`` test scans inverted by ``invert_steps`` steps
  and scored against the ground truth, beside the training split's per-ring
  keep-rate table (:func:`restoration`'s ``ground_truth``). Writes
  ``OUT/final_evaluation.json`` and ``OUT/final_evaluation.png`` (a row per
  test scan, titled panels: the target scan, the inverted x_tilde and
  measurability, and, with ground truth, the true return probability; colour
  bars in metres and probability); returns the record."""
  sensor = params.sensor
  test = arrays.load_split(data_dir, 'test', sensor)
  record = {'data': data_dir}
  if num_synthesis:
    rec = synthesis(params, test, num=num_synthesis, points=points, seeds=1,
                    progress=progress)
    row = rec['rows'][row_label(params, rec['tolerance'])]
    record['synthesis'] = {'num': rec['num'], 'points': points,
                           **{k: v[0] for k, v in row.items()}}
  if num_invert:
    n = min(num_invert, len(test))
    truth = arrays.load_ground_truth(data_dir, 'test', sensor, n)
    ring_keep = (training_ring_keep(data_dir, sensor)
                 if truth is not None and params.variant.has_measurability else None)
    shown = []  # (scan, x_tilde, measurability) of the first scans

    def keep_shown(start, clean, target, res):
      for i in range(min(len(clean), picture_scans - start)):
        shown.append((clean[i], res['inv_depth'][i], res['measurability'][i]))

    rec = restoration(params, test[:n], num_steps=invert_steps, truth=truth,
                      ring_keep=ring_keep, each=keep_shown, progress=progress)
    record['restoration'] = {'num': rec['num'], 'steps': invert_steps, **rec['mean']}
    if 'ground_truth' in rec:
      record['ground_truth'] = {k: v for k, v in rec['ground_truth'].items()
                                if k != 'reliability'}
    if shown:  # (picture_scans=0: none)
      scans, inverted, measurability = zip(*shown)
      columns = [writers.Column('target scan', writers.DEPTH, scans),
                 writers.Column('reconstruction x_tilde', writers.DEPTH, inverted),
                 writers.Column('measurability', writers.PROBABILITY, measurability,
                                'probability of a return, as inverted')]
      if truth is not None:
        columns.append(writers.Column('true return probability', writers.PROBABILITY,
                                      1.0 - truth[1][:len(shown)],
                                      "probability of a return, the simulator's"))
      writers.save_figure(writers.scan_figure(columns, sensor, row_label='test scan'),
                          os.path.join(out, AFTER_TRAINING + '.png'))
  os.makedirs(out, exist_ok=True)
  with open(os.path.join(out, AFTER_TRAINING + '.json'), 'w') as f:
    json.dump(record, f, indent=2)
  return record


def training_ring_keep(data_dir: str, sensor) -> np.ndarray:
  """(H,) the keep rate per ring of a prepared dataset's training split (its
  first RING_TABLE_SCANS scans): the table a measurability should beat."""
  return ground_truth.ring_keep_rate(
      arrays.load_split(data_dir, 'train', sensor)[:RING_TABLE_SCANS], sensor)


def placement_lines(gt: dict) -> list[str]:
  """One line per map of a ``ground_truth`` record (restoration's): the
  measurability and, where present, the per-ring table."""
  num = lambda v: f'{v:.3f}' if np.isfinite(v) else 'n/a'  # n/a: no pair to rank
  lines = []
  for name, key in (('measurability', 'placement'),
                    ("the training split's keep rate per ring", 'ring_table')):
    if key in gt:
      m = gt[key]
      lines.append(f'{name}: AUC of the drops on surfaces < 40 m {num(m["auc_near"])}, '
                   f'within rings {num(m["auc_near_within_ring"])}, ECE {m["ece"]:.4f}')
  return lines


def summary(record: dict) -> str:
  """The lines a training ends with, of :func:`after_training`'s record."""
  lines = []
  if 'synthesis' in record:
    m = record['synthesis']
    lines.append(f'Table II on {m["num"]} test scans ({m["points"]} points): JSD x1e2 '
                 f'{100 * m["jsd"]:.1f}, COV {100 * m["cov"]:.1f}%, MMD x1e3 '
                 f'{1e3 * m["mmd"]:.1f}, 1-NNA {100 * m["1nna"]:.1f}%, SWD {m["swd"]:.3f}')
  lines += placement_lines(record.get('ground_truth', {}))
  lines.append(f'written: {AFTER_TRAINING}.json, {AFTER_TRAINING}.png')
  return '\n'.join(lines)
