"""Sampling scans from a trained generator: ``dusty_jax.sample``."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from dusty_jax import models, projection


def decode_scan(params: models.GeneratorParams, scan):
  """Measured depth, validity and points (in metres) of generated scans."""
  depth, valid = projection.decode(scan, params.sensor, params.tolerance)
  points = projection.to_points(depth, params.angles)
  return depth, valid, points


def generate(params: models.GeneratorParams, z, key, train: bool = False,
             impl: str | None = None):
  """What the generator makes of latents ``z`` (B, latent_dim), as a dict.

  ``key`` draws the Gumbel noise of the sampled mask (``train=False``: the
  test-time mask, DUSty-II's image-level mask noise-free). Latent for
  latent, the outputs compare with another implementation's.

  Keys: ``inv_depth`` (x_tilde, complete), ``measurability`` (probability of
  a return; all ones for the baseline), ``mask`` (sampled), ``scan`` (x),
  ``depth`` (metres, 0 where dropped), ``valid`` and ``points`` (B, H, W, 3).
  """
  raw = params.module(impl).apply(params.variables, z)
  out = models.render(params.model, raw, key, params.tau, train)
  if params.model == 'baseline':
    out['measurability'] = jnp.ones_like(out['inv_depth'])
  else:
    out['measurability'] = models.measurability(params.model, out['logit'])
  depth, valid, points = decode_scan(params, out['scan'])
  out.update(depth=depth, valid=valid, points=points)
  return out


@functools.partial(jax.jit, static_argnames=('num', 'impl'))
def sample(params: models.GeneratorParams, key, num: int, impl: str | None = None):
  """Draws ``num`` scans: z ~ N(0, I), test-time Gumbel sampling.

  Returns the dict of :func:`generate`.
  """
  kz, kmask = jax.random.split(key)
  z = jax.random.normal(kz, (num, params.latent_dim))
  return generate(params, z, kmask, impl=impl)
