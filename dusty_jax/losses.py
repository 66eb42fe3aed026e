"""Non-saturating GAN losses and the R1 penalty."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from dusty_jax import errors


def d_loss(real_logits, fake_logits):
  """-log D(x_real) - log(1 - D(G(z))), with D = sigmoid of the logits.

  Finite for any finite logits (softplus saturates linearly); concrete
  logits (outside jit) must be finite (errors.InputError)."""
  errors.check_finite(real_logits, 'real logits')
  errors.check_finite(fake_logits, 'fake logits')
  return jax.nn.softplus(-real_logits).mean() + jax.nn.softplus(fake_logits).mean()


def g_loss(fake_logits):
  """Non-saturating generator loss -log D(G(z)); finite logits as
  :func:`d_loss`."""
  errors.check_finite(fake_logits, 'fake logits')
  return jax.nn.softplus(-fake_logits).mean()


def r1_penalty(d_fn, x):
  """E ||grad_x D(x)||^2 over the batch (multiply by gamma / 2).

  ``d_fn`` maps a batch of scans to logits; ``x`` are real scans as the
  discriminator sees them (after augmentation).
  """
  grad = jax.grad(lambda x: d_fn(x).sum())(x)
  return jnp.sum(jnp.square(grad), axis=tuple(range(1, x.ndim))).mean()
