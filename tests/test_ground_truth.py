"""Disentanglement scores against simulator ground truth."""

import numpy as np
import pytest

from dusty_jax import codec
from dusty_jax.metrics import ground_truth
from dusty_jax.sensor import tiny_sensor


def test_roc_auc_matches_pairwise_count():
  rng = np.random.default_rng(0)
  score = rng.integers(0, 5, 300).astype(float)  # many ties
  label = rng.uniform(size=300) < 0.3
  pos, neg = score[label], score[~label]
  brute = ((pos[:, None] > neg[None]).sum() + 0.5 * (pos[:, None] == neg[None]).sum()) / (
      len(pos) * len(neg))
  assert ground_truth.roc_auc(score, label) == pytest.approx(brute, abs=1e-12)
  assert ground_truth.roc_auc(label.astype(float), label) == 1.0
  assert np.isnan(ground_truth.roc_auc(score, np.ones(300, bool)))


def _scene(seed=0):
  sensor = tiny_sensor(16, 64)
  rng = np.random.default_rng(seed)
  complete = rng.uniform(2.0, 100.0, (3,) + sensor.shape)
  complete[:, :3] = 0.0  # sky: no surface
  p = rng.uniform(0.0, 0.5, complete.shape)
  p[:, :3] = 1.0
  observed = np.where(rng.uniform(size=p.shape) < p, 0.0, complete)
  return sensor, complete, p, observed


def test_auc_within_rows_counts_only_pairs_of_one_row():
  rng = np.random.default_rng(3)
  b, h, w = 3, 5, 7
  label = rng.uniform(size=(b, h, w)) < np.linspace(0.1, 0.9, h)[:, None]
  mask = rng.uniform(size=(b, h, w)) < 0.8
  score = rng.normal(size=(b, h, w)) + label * np.arange(h)[:, None] * 0.5
  wins = 0.0
  for r in range(h):  # brute force over the pairs within each row
    s, l = score[:, r][mask[:, r]], label[:, r][mask[:, r]]
    for sp in s[l]:
      wins += (sp > s[~l]).sum() + 0.5 * (sp == s[~l]).sum()
  pairs = sum(label[:, r][mask[:, r]].sum() * (~label[:, r][mask[:, r]]).sum()
              for r in range(h))
  assert ground_truth.roc_auc_within_rows(score, label, mask) == pytest.approx(wins / pairs)
  # A score that is constant per row knows nothing within a row; the pooled
  # AUC rewards it for the rows' differing rates.
  per_row = np.broadcast_to(np.linspace(0.1, 0.9, h)[:, None], (b, h, w))
  assert ground_truth.roc_auc_within_rows(per_row, label, mask) == 0.5
  assert ground_truth.roc_auc(per_row[mask], label[mask]) > 0.6


def test_ring_table_knows_the_rings_and_nothing_within_them():
  sensor, complete, p, observed = _scene(1)
  p = p.copy()
  p[:, 3:] = np.linspace(0.05, 0.6, sensor.shape[0] - 3)[:, None]  # drops by ring only
  rng = np.random.default_rng(4)
  observed = np.where(rng.uniform(size=p.shape) < p, 0.0, complete)
  keep = ground_truth.ring_keep_rate(observed, sensor)
  assert keep.shape == (sensor.shape[0],)
  assert np.allclose(keep, (observed > 0).mean(axis=(0, 2)))  # every range is in the sensor's
  table = ground_truth.ring_table_scores(sensor, keep, observed, complete, p)
  assert table['auc_near_within_ring'] == 0.5
  assert table['auc_surface'] > 0.6  # the rings' rates differ
  # Its scores are measurability_scores' of the broadcast table.
  same = ground_truth.measurability_scores(
      sensor, np.broadcast_to(keep[None, :, None], observed.shape), observed, complete, p)
  assert table['auc_near'] == same['auc_near'] and table['ece'] == same['ece']
  with pytest.raises(ValueError, match='rings'):
    ground_truth.ring_table_scores(sensor, keep[:-1], observed, complete, p)


def test_perfect_model_scores_perfectly():
  sensor, complete, p, observed = _scene()
  x = np.asarray(codec.encode(complete, sensor))
  out = ground_truth.disentanglement(sensor, x, 1.0 - p, observed, complete, p)
  assert out['completion']['pixels'] == int(((complete > 0) & (observed == 0)).sum()) > 0
  assert out['completion']['abs_rel'] < 1e-5 and out['fit']['abs_rel'] < 1e-5
  assert out['coverage'] == 1.0
  assert out['measurability']['ece'] < 1e-9
  assert out['measurability']['auc'] > 0.6


def test_baseline_rendering_drops_is_not_completion_and_errors_grow():
  sensor, complete, p, observed = _scene(1)
  x_obs = np.asarray(codec.encode(observed, sensor))  # drops at ALPHA
  out = ground_truth.disentanglement(sensor, x_obs, np.ones_like(p), observed,
                                     complete, p, renders_drop=x_obs <= -1.0)
  assert out['coverage'] == 0.0 and out['completion']['pixels'] == 0
  assert out['fit']['abs_rel'] < 1e-5
  assert out['measurability']['auc'] == 0.5  # a constant predicts nothing
  # Read as DUSty's x_tilde, ALPHA at a dropped surface is the far end: wrong.
  out = ground_truth.disentanglement(sensor, x_obs, np.ones_like(p), observed,
                                     complete, p)
  assert out['coverage'] == 1.0 and out['completion']['abs_rel'] > 0.1
