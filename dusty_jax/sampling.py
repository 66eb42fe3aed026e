"""Sampling scans from a trained generator: ``dusty_jax.sample``."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from dusty_jax import codec, errors, sensor
from dusty_jax.generator import GeneratorParams

# The largest latent component generate() takes. Latents are draws of
# N(0, I) (or points on the sphere of radius sqrt(d) that invert keeps):
# 1e4 standard deviations is far beyond any of them, and far larger ones
# overflow float32 inside the network (1e38 makes the whole scan NaN).
MAX_LATENT = 1e4


def decode_scan(params: GeneratorParams, scan):
  """Measured depth, validity and points (in metres) of generated scans."""
  depth, valid = codec.decode(scan, params.sensor, params.tolerance)
  points = codec.to_points(depth, params.angles)
  return depth, valid, points


def generate(params: GeneratorParams, z, key, train: bool = False,
             impl: str | None = None):
  """What the generator makes of latents ``z`` (B, latent_dim), as a dict.

  ``key`` draws the Gumbel noise of the sampled mask (``train=False``: the
  test-time mask, DUSty-II's image-level mask noise-free). Latent for
  latent, the outputs compare with another implementation's.

  Keys: ``inv_depth`` (x_tilde, complete), ``measurability`` (probability of
  a return; all ones for the baseline), ``mask`` (sampled), ``scan`` (x),
  ``depth`` (metres, 0 where dropped), ``valid`` and ``points`` (B, H, W, 3).
  Compiled (jit) once per shape; inside other jitted code it inlines.

  ``z`` must be finite with no component beyond MAX_LATENT (else
  errors.InputError); any float dtype is cast to float32, as are
  half-precision ``params`` (:func:`full_precision`).
  """
  if jnp.ndim(z) != 2 or jnp.shape(z)[1] != params.latent_dim:
    raise ValueError(f'z of shape {jnp.shape(z)}: expected latents of shape (B, '
                     f"{params.latent_dim}), {params.latent_dim} being this generator's "
                     'latent_dim')
  check_latents(z, 'z')
  return _generate(full_precision(params), jnp.asarray(z, jnp.float32), as_key(key),
                   train, impl)


def check_latents(z, what: str):
  """``z`` unchanged if finite and within MAX_LATENT, else errors.InputError
  naming ``what`` and the value (a tracer passes unread)."""
  errors.check_finite(z, what)
  if errors.is_concrete(z) and np.size(z):
    big = float(np.max(np.abs(np.asarray(z, np.float32))))
    if big > MAX_LATENT:
      raise errors.InputError(
          f'{what}: a component of magnitude {big:.3g}, beyond {MAX_LATENT:g} '
          '(sampling.MAX_LATENT): latents are draws of N(0, I); the network '
          'overflows float32 far beyond that')
  return z


def full_precision(params: GeneratorParams) -> GeneratorParams:
  """``params`` with float16 and bfloat16 arrays (weights, angles, encoder)
  cast to float32 (errors.widen_half); the same object when none is. A
  half-precision generator computes as the float32 generator of its
  rounded weights."""
  arrays = (params.variables, params.angles, params.encoder)
  wide = errors.widen_half(arrays)
  if wide is arrays:
    return params
  return params.replace(variables=wide[0], angles=wide[1], encoder=wide[2])


@functools.partial(jax.jit, static_argnames=('train', 'impl'))
def _generate(params, z, key, train, impl):
  raw = params.module(impl).apply(params.variables, z)
  out = params.variant.compose(raw, key, params.tau, train)
  out['measurability'] = params.variant.measurability_of(out)
  depth, valid, points = decode_scan(params, out['scan'])
  out.update(depth=depth, valid=valid, points=points)
  return out


def as_key(key, what: str = 'key'):
  """A typed PRNG key (array); legacy uint32 keys are wrapped, anything
  else is refused with a message."""
  if key is None:
    return jax.random.key(0)
  if isinstance(key, (int, np.integer)):
    raise TypeError(f'{what}: got the int {key}; pass jax.random.key({key})')
  key = jnp.asarray(key) if not hasattr(key, 'dtype') else key
  if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
    return key
  if key.dtype == jnp.uint32 and key.ndim >= 1 and key.shape[-1] == 2:
    return jax.random.wrap_key_data(key)  # legacy jax.random.PRNGKey(...)
  raise TypeError(f'{what}: expected a key from jax.random.key(seed), got an '
                  f'array of dtype {key.dtype} and shape {key.shape}')


def check_params(params: GeneratorParams):
  sensor.check_angles(params.angles, params.sensor.shape,
                      f'generator of sensor {params.sensor.name!r}: ')


def sample(params: GeneratorParams, key, num: int, impl: str | None = None):
  """Draws ``num`` scans: z ~ N(0, I), test-time Gumbel sampling.

  ``key``: from ``jax.random.key`` (a legacy ``PRNGKey`` is accepted).
  Returns the dict of :func:`generate`; ``num=0`` gives its arrays with a
  leading axis of 0 (as numpy, and as ``invert`` of an empty batch).
  """
  num = errors.check_count(num, 'num')
  check_params(params)
  key = as_key(key)
  if key.shape != ():
    raise ValueError(f'key: expected one key, got shape {key.shape}')
  return _sample(full_precision(params), key, num, impl)


@functools.partial(jax.jit, static_argnames=('num', 'impl'))
def _sample(params, key, num, impl):
  kz, kmask = jax.random.split(key)
  z = jax.random.normal(kz, (num, params.latent_dim))
  return generate(params, z, kmask, impl=impl)


def sample_scans(params: GeneratorParams, key, num: int, batch: int = 64) -> np.ndarray:
  """(num, H, W) sampled scans x as numpy, drawn ``batch`` at a time (the
  batch starting at i with ``fold_in(key, i)``)."""
  key = as_key(key)
  out = [np.zeros((0,) + tuple(params.sensor.shape), np.float32)]
  for i in range(0, num, batch):
    n = min(batch, num - i)
    out.append(np.asarray(sample(params, jax.random.fold_in(key, i), n)['scan']))
  return np.concatenate(out)
