"""Straight-through Gumbel-sigmoid, at pixel level and image level.

The difference of two Gumbel(0, 1) draws is Logistic(0, 1), drawn here by the
inverse CDF ``log(u) - log(1 - u)`` with ``u`` kept inside [EPS, 1 - EPS]: a
uniform draw of exactly 0 or 1 gives finite noise (about +-16.6), never inf.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from dusty_jax import errors

EPS = 2.0 ** -24  # smallest step below 1 in float32: 1 - EPS is exact.
TINY = float(np.finfo(np.float32).tiny)  # float32's smallest normal number

# The temperatures a training can use (configs.validate). The mask's
# straight-through gradient is sigmoid'((logit + noise) / tau) / tau, and
# float32's sigmoid saturates beyond |logit + noise| = 17 tau: below 1e-2 the
# gradient reaches fewer than 9% of pixels (the logistic density is at most
# 1/4), spikes of up to 25 there. Above 1e2 it lies within 1% of 1 / (4 tau)
# wherever |logit + noise| < 20, whatever the logit: it no longer says which
# pixels should drop. The forward mask is the same for every tau > 0.
TAU_RANGE = (1e-2, 1e2)


def check_tau(tau, what: str = 'tau'):
  """``tau`` unchanged if it is a finite float32 number >= TINY (smaller
  ones flush to 0 and divide the logits into NaN; inf drops every pixel);
  else errors.InputError naming it. A tracer passes unread."""
  if errors.is_concrete(tau) and not (np.ndim(tau) == 0 and TINY <= float(tau) < math.inf):
    raise errors.InputError(f'{what}={tau!r}: the Gumbel temperature must be a finite '
                            f'number >= {TINY:.4g} (float32\'s smallest normal); '
                            f'training uses [{TAU_RANGE[0]:g}, {TAU_RANGE[1]:g}]')
  return tau


def logistic_from_uniform(u):
  u = jnp.clip(u, EPS, 1.0 - EPS)
  return jnp.log(u) - jnp.log1p(-u)


def logistic_noise(key, shape):
  return logistic_from_uniform(jax.random.uniform(key, shape))


def straight_through(logits, noise, tau: float = 1.0):
  """Hard mask in the forward pass, the soft mask's gradient in the backward.

  ``soft = sigmoid((logits + noise) / tau)``; forward value ``z > 0`` (``soft > 0.5``, the authors' threshold).
  Stable for finite logits of any magnitude and any tau that
  :func:`check_tau` accepts: sigmoid saturates to an exact 0 or 1 with a
  zero (not NaN) gradient. Concrete logits (outside jit) must be finite
  (errors.InputError): a NaN logit has no mask.
  """
  check_tau(tau)
  errors.check_finite(logits, 'logits')
  z = (logits + noise) / tau
  soft = jax.nn.sigmoid(z)
  hard = (z > 0).astype(soft.dtype)
  return hard + (soft - jax.lax.stop_gradient(soft))  # exactly hard forward.


def pixel_mask(key, logits, tau: float = 1.0):
  """Independent noise per pixel: logits (B, H, W)."""
  return straight_through(logits, logistic_noise(key, logits.shape), tau)


def image_mask(key, logits, tau: float = 1.0, train: bool = True):
  """One noise draw per image shared by its pixels; deterministic at test."""
  if not train:
    errors.check_finite(logits, 'logits')
    return (logits > 0).astype(logits.dtype)
  noise = logistic_noise(key, logits.shape[:1] + (1,) * (logits.ndim - 1))
  return straight_through(logits, noise, tau)
