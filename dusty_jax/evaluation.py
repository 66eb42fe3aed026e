"""Evaluation as library code: the paper's Table II (synthesis) of a trained
generator against a dataset's splits.

The evaluate tool calls :func:`synthesis` (and :func:`tune_tolerance` for
the baseline's beta), as benchmarks should, so that two reports of one
metric cannot differ by a subset rule, a seed or a training-set row. The
test subset follows the protocol (metrics/protocol.py: ``subset``); the
generated set of seed s is sampled with ``key(SAMPLE_SEED + s)``.
"""

from __future__ import annotations

import sys

import jax
import numpy as np
import tqdm

from dusty_jax import codec, sampling
from dusty_jax.generator import GeneratorParams
from dusty_jax.metrics import protocol

SAMPLE_SEED = 1000  # generated set s is sampled with key(SAMPLE_SEED + s).
TRAINING_ROW = 'training set'  # the label of the train vs test row


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
  return {**protocol.provenance(protocol_name, n, points, provenance_seeds,
                                protocol.SUBSET_RULES[protocol_name], sensor),
          'tolerance': tol, 'rows': rows}
