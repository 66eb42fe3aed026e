"""Disentanglement against a simulator's ground truth.

A simulated scan comes with the depth a perfect sensor would see (the
complete depth, 0 where a ray hits nothing) and the true probability of
each point-drop. After inverting an observed scan, DUSty's x_tilde should
match the complete depth everywhere a surface was hit, dropped or not, and
its measurability should match the true return probability 1 - p_drop.

Pixel sets, per scan:
  * fit: the observed scan's valid pixels;
  * completion: pixels the sensor dropped although a surface was in range
    (complete depth valid, observation dropped): what only a model of the
    complete scene can fill.
The baseline has no x_tilde apart from its scan: where it renders a drop
(x_tilde <= ALPHA + tolerance) a completion pixel counts as not completed;
``coverage`` is the completed fraction and errors are over covered pixels.
DUSty's x_tilde is complete by construction (coverage 1): x_tilde = ALPHA
there means the far end of the range, not a drop.

Measurability (predicted P(return)) is scored by ECE against the true
return probability, and by the Brier score and ROC AUC against the returns
actually observed, on all pixels and on surface pixels only (sky pixels,
which never return, are easy).
"""

from __future__ import annotations

import numpy as np

from dusty_jax import codec
from dusty_jax.metrics import calibration
from dusty_jax.sensor import SensorSpec


def roc_auc(score, label) -> float:
  """Area under the ROC curve: P(score of a positive > score of a negative),
  ties counting one half (Mann-Whitney U with average ranks)."""
  score = np.asarray(score, np.float64).ravel()
  label = np.asarray(label, bool).ravel()
  n_pos = int(label.sum())
  n_neg = label.size - n_pos
  if n_pos == 0 or n_neg == 0:
    return float('nan')
  order = np.argsort(score, kind='stable')
  ranks = np.empty(score.size, np.float64)
  _, first, counts = np.unique(score[order], return_index=True, return_counts=True)
  # Average rank (1-based) of each group of ties.
  avg = first + (counts + 1) / 2.0
  ranks[order] = np.repeat(avg, counts)
  return float((ranks[label].sum() - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))


def roc_auc_within_rows(score, label, mask) -> float:
  """ROC AUC of ``score`` against ``label`` within each image row (ring) over
  ``mask`` (B, H, W), averaged over the rows that hold both classes,
  weighted by their pairs (positives x negatives): pooled within-row
  pairs only. A score that is constant per row scores 0.5; it measures
  what a measurability knows beyond which laser a pixel belongs to."""
  score, label, mask = (np.asarray(a) for a in (score, label, mask))
  total = weight = 0.0
  for r in range(score.shape[1]):
    m = mask[:, r].astype(bool)
    lab = label[:, r][m].astype(bool)
    pairs = float(lab.sum()) * float((~lab).sum())
    if pairs:
      total += pairs * roc_auc(score[:, r][m], lab)
      weight += pairs
  return total / weight if weight else float('nan')


def pooled_errors(pred, target, mask) -> dict:
  """MAE (m) and AbsRel over ``mask``, pooled over all scans' pixels (not
  per scan, unlike Table III's metrics/depth.py)."""
  mask = np.asarray(mask, bool)
  if not mask.any():
    return {'mae_m': float('nan'), 'abs_rel': float('nan'), 'pixels': 0}
  err = np.abs(pred[mask] - target[mask])
  return {'mae_m': float(err.mean()), 'abs_rel': float((err / target[mask]).mean()),
          'pixels': int(mask.sum())}


def completion(sensor: SensorSpec, inv_depth, complete, region, renders_drop=None):
  """(errors, coverage) of x_tilde against the complete depth over ``region``.

  Pixels the model renders as dropped in x_tilde itself (``renders_drop``,
  the baseline) are not completed: ``coverage`` is the completed fraction of
  ``region`` and the errors are over completed pixels.
  """
  region = np.asarray(region, bool)
  covered = region if renders_drop is None else region & ~np.asarray(renders_drop, bool)
  pred = np.asarray(codec.complete_depth(inv_depth, sensor), np.float64)
  errors = pooled_errors(pred, np.asarray(complete, np.float64), covered)
  return errors, float(covered.sum() / max(region.sum(), 1))


NEAR_M = 40.0  # 'near' surfaces: where a drop is visible in inverse depth.


def disentanglement(sensor: SensorSpec, inv_depth, measurability, observed, complete,
                    drop_prob, renders_drop=None, bins: int = 10,
                    near: float = NEAR_M) -> dict:
  """Scores an inversion against ground truth.

  Args:
    sensor: the SensorSpec.
    inv_depth: (B, H, W) x_tilde of the inversion.
    measurability: (B, H, W) predicted probability of a return.
    observed: (B, H, W) metric depth the model was fitted to (0: dropped).
    complete: (B, H, W) the simulator's complete depth (0: no surface).
    drop_prob: (B, H, W) the true probability of a drop.
    renders_drop: optional (B, H, W) bool, pixels the model renders as
      dropped in x_tilde itself (the baseline): not completed there.

  Returns:
    dict with ``completion`` and ``fit`` (MAE in metres, AbsRel, pixels),
    ``coverage``, and ``measurability`` scores (ECE, Brier, AUC; all pixels,
    surface pixels, and surfaces nearer than ``near`` metres) with the
    reliability curve.
  """
  observed = np.asarray(observed, np.float64)
  complete = np.asarray(complete, np.float64)
  valid_obs = np.asarray(codec.valid_depth(observed, sensor))
  surface = np.asarray(codec.valid_depth(complete, sensor))
  filled, coverage = completion(sensor, inv_depth, complete, surface & ~valid_obs,
                                renders_drop)
  pred = np.asarray(codec.complete_depth(inv_depth, sensor), np.float64)
  return {
      'completion': filled,
      'fit': pooled_errors(pred, observed, valid_obs),
      'coverage': coverage,
      'measurability': measurability_scores(sensor, measurability, observed, complete,
                                            drop_prob, bins, near),
  }


def ring_keep_rate(observed, sensor: SensorSpec) -> np.ndarray:
  """(H,) the fraction of pixels that returned a point in each ring (row) of
  the metric depth scans ``observed`` (B, H, W; 0 or out of range: dropped)."""
  observed = np.asarray(observed, np.float32)
  if not len(observed):
    raise ValueError('ring_keep_rate: no scans to count returns in')
  return np.asarray(codec.valid_depth(observed, sensor), np.float64).mean(axis=(0, 2))


def ring_table_scores(sensor: SensorSpec, ring_keep, observed, complete, drop_prob,
                      bins: int = 10, near: float = NEAR_M) -> dict:
  """:func:`measurability_scores` of a model-free table: each pixel's
  measurability is its ring's keep rate ``ring_keep`` (H,), e.g. the
  training split's (:func:`ring_keep_rate`), scored on other scans. A
  measurability earns its place by beating it; within rings it scores 0.5
  by construction."""
  ring_keep = np.asarray(ring_keep, np.float64)
  observed = np.asarray(observed)
  if ring_keep.shape != observed.shape[1:2]:
    raise ValueError(f'ring_keep has shape {ring_keep.shape}; the scans have '
                     f'{observed.shape[1]} rings')
  table = np.broadcast_to(ring_keep[None, :, None], observed.shape)
  return measurability_scores(sensor, table, observed, complete, drop_prob, bins, near)


def measurability_scores(sensor: SensorSpec, measurability, observed, complete, drop_prob,
                         bins: int = 10, near: float = NEAR_M) -> dict:
  """A measurability (B, H, W) against the returns of ``observed`` and the
  true keep probability 1 - ``drop_prob``: ECE, Brier and ROC AUC over all
  pixels, surface pixels (``complete`` > 0) and surfaces nearer than
  ``near`` metres (there also the AUC within rings), and the reliability
  curve. Arguments as :func:`disentanglement`'s."""
  complete = np.asarray(complete, np.float64)
  valid_obs = np.asarray(codec.valid_depth(np.asarray(observed, np.float64), sensor))
  surface = np.asarray(codec.valid_depth(complete, sensor))
  near_surface = surface & (complete < near)
  m = np.clip(np.asarray(measurability, np.float64), 0.0, 1.0)
  truth = 1.0 - np.asarray(drop_prob, np.float64)
  returned = valid_obs.astype(np.float64)
  cal = calibration.reliability(m, truth, bins=bins)
  cal_surface = calibration.reliability(m, truth, bins=bins, mask=surface)
  return {
      'ece': cal['ece'],
      'ece_surface': cal_surface['ece'],
      'brier': float(np.mean(np.square(m - returned))),
      'brier_surface': float(np.mean(np.square(m - returned)[surface])),
      'auc': roc_auc(m, valid_obs),
      'auc_surface': roc_auc(m[surface], valid_obs[surface]),
      'auc_near': roc_auc(m[near_surface], valid_obs[near_surface]),
      'auc_near_within_ring': roc_auc_within_rows(m, valid_obs, near_surface),
      'ece_near': calibration.reliability(m, truth, bins=bins, mask=near_surface)['ece'],
      'reliability': {k: np.asarray(v).tolist() for k, v in cal.items() if k != 'ece'},
  }
