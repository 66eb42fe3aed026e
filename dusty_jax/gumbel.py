"""Straight-through Gumbel-sigmoid, at pixel level and image level.

The difference of two Gumbel(0, 1) draws is Logistic(0, 1), drawn here by the
inverse CDF ``log(u) - log(1 - u)`` with ``u`` kept inside [EPS, 1 - EPS]: a
uniform draw of exactly 0 or 1 gives finite noise (about +-16.6), never inf.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

EPS = 2.0 ** -24  # smallest step below 1 in float32: 1 - EPS is exact.


def logistic_from_uniform(u):
  u = jnp.clip(u, EPS, 1.0 - EPS)
  return jnp.log(u) - jnp.log1p(-u)


def logistic_noise(key, shape):
  return logistic_from_uniform(jax.random.uniform(key, shape))


def straight_through(logits, noise, tau: float = 1.0):
  """Hard mask in the forward pass, the soft mask's gradient in the backward.

  ``soft = sigmoid((logits + noise) / tau)``; forward value ``z > 0`` (``soft > 0.5``, the authors' threshold).
  Stable for logits of any magnitude and small tau: sigmoid saturates to an
  exact 0 or 1 with a zero (not NaN) gradient.
  """
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
    return (logits > 0).astype(logits.dtype)
  noise = logistic_noise(key, logits.shape[:1] + (1,) * (logits.ndim - 1))
  return straight_through(logits, noise, tau)
