"""Calibration of the measurability map against a simulator's true drop
probability: reliability curve and expected calibration error (ECE).

The measurability is the predicted probability that a pixel returns a
point; the truth is ``1 - drop_prob``. Pixels are binned by prediction into
equal-width bins over [0, 1]; per bin the curve gives the mean prediction,
the mean true probability and the count; ECE is the count-weighted mean of
|mean prediction - mean truth|.
"""

from __future__ import annotations

import numpy as np

from dusty_jax import errors


def reliability(pred, truth, bins: int = 10, mask=None):
  """Returns dict of per-bin 'pred', 'truth', 'count' arrays and 'ece'.
  Both must be finite probabilities in [0, 1] (errors.InputError);
  ``mask`` selects the pixels, checked after it."""
  pred = np.asarray(pred, np.float64).ravel()
  truth = np.asarray(truth, np.float64).ravel()
  if pred.shape != truth.shape:
    raise ValueError(f'prediction and truth differ in size: {pred.shape} vs {truth.shape}')
  if mask is not None:
    keep = np.asarray(mask, bool).ravel()
    pred, truth = pred[keep], truth[keep]
  if pred.size == 0:
    raise ValueError('calibration needs at least one pixel')
  for v, what in ((pred, 'predictions'), (truth, 'true probabilities')):
    errors.check_finite(v, what, 'give probabilities in [0, 1]')
    if v.min() < 0 or v.max() > 1:
      raise errors.InputError(f'{what} lie in [{v.min():.4g}, {v.max():.4g}]: '
                              'probabilities must lie in [0, 1]')
  idx = np.minimum((np.clip(pred, 0, 1) * bins).astype(int), bins - 1)
  count = np.bincount(idx, minlength=bins).astype(np.float64)
  sp = np.bincount(idx, pred, minlength=bins)
  st = np.bincount(idx, truth, minlength=bins)
  with np.errstate(invalid='ignore', divide='ignore'):
    mp, mt = sp / count, st / count
  ece = float(np.nansum(count / count.sum() * np.abs(mp - mt)))
  return {'pred': mp, 'truth': mt, 'count': count, 'ece': ece}
