"""Depth errors over a target's valid pixels (metres), as in depth estimation.

AbsRel, SqRel, RMSE, RMSE log and the accuracies delta < 1.25^i, i = 1..3.
Computed per scan over the pixels where ``mask`` is set; a scan with no such
pixel gets NaN metrics and a ``count`` of 0 (callers warn on it).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from dusty_jax import errors

NAMES = ('abs_rel', 'sq_rel', 'rmse', 'rmse_log', 'delta1', 'delta2', 'delta3')


def depth_errors(pred, target, mask, eps: float = 1e-6):
  """Per-scan dict of (B,) metrics: pred, target (B, H, W) metres, mask bool.
  Concrete inputs must be finite where the mask is set (errors.InputError);
  a prediction below ``eps`` (0: a drop) counts as ``eps``."""
  m = jnp.asarray(mask, bool)
  if all(map(errors.is_concrete, (pred, target, mask))):
    keep = np.broadcast_to(np.asarray(m), np.shape(pred))
    for v, what in ((pred, 'predicted depth'), (target, 'target depth')):
      errors.check_finite(np.asarray(v)[keep], f'{what} inside the mask')
  n = m.sum(axis=(-2, -1))
  safe_n = jnp.maximum(n, 1)
  t = jnp.where(m, target, 1.0)
  p = jnp.where(m, jnp.maximum(pred, eps), 1.0)
  mean = lambda v: jnp.where(n > 0, jnp.where(m, v, 0).sum((-2, -1)) / safe_n, jnp.nan)
  ratio = jnp.maximum(p / t, t / p)
  out = {
      'abs_rel': mean(jnp.abs(p - t) / t),
      'sq_rel': mean(jnp.square(p - t) / t),
      'rmse': jnp.sqrt(mean(jnp.square(p - t))),
      'rmse_log': jnp.sqrt(mean(jnp.square(jnp.log(p) - jnp.log(t)))),
  }
  for i in (1, 2, 3):
    out[f'delta{i}'] = mean((ratio < 1.25 ** i).astype(jnp.float32))
  out['count'] = n
  return out
