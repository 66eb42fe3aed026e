"""GAN inversion: reconstruct scans by searching the generator's latent space.

``invert(params, scan)`` minimises the L1 distance between the target's
normalised inverse depth and the generator's complete inverse depth x_tilde
over the target's valid pixels, with the authors' schedule (StyleGAN2's
projector): Adam at lr 0.1 with a 5% linear ramp-up and a 25% cosine
ramp-down, Gaussian latent noise of std 0.05 * max(0, 1 - t / 0.75)^2 at
progress t, and after every update the latent projected back onto the sphere
of radius sqrt(d). Each scan's search is independent (vmapped), so a scan
gives the same result alone or inside a batch.

The authors compute the L1 on inverse depth in [0, 1]; here it is on the
[-1, 1] of the codec, twice as large. Adam is invariant to that scale (up
to its eps), so the search follows the same path.
"""

from __future__ import annotations

import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax

from dusty_jax import sampling
from dusty_jax.codec import ALPHA
from dusty_jax.generator import GeneratorParams

LR = 0.1
RAMP_UP = 0.05
RAMP_DOWN = 0.25
NOISE_SCALE = 0.05
NOISE_RAMP = 0.75


def lr_schedule(num_steps: int, lr: float = LR):
  """StyleGAN2's projector schedule: linear ramp-up, flat, cosine ramp-down.

  Over progress t = step / num_steps: lr * min(1, t / RAMP_UP) times
  0.5 - 0.5 cos(pi min(1, (1 - t) / RAMP_DOWN)). The boundaries may fall
  between steps; the pieces meet at lr, so that is harmless.
  """
  up = RAMP_UP * num_steps
  down = RAMP_DOWN * num_steps
  return optax.join_schedules(
      [optax.linear_schedule(0.0, lr, up), optax.constant_schedule(lr),
       optax.cosine_decay_schedule(lr, down)],
      boundaries=[up, num_steps - down])


@functools.partial(jnp.vectorize, signature='(d)->(d)')
def project(z):
  """Onto the sphere of radius sqrt(d), along the last axis.

  z is first divided by its largest magnitude (the projection does not
  change), so a norm whose square would underflow float32 still gives a
  point on the sphere. z = 0, whose nearest point on the sphere could be
  any, goes to the all-ones point, whose norm is sqrt(d).
  """
  big = jnp.max(jnp.abs(z))
  z = jnp.where(big > 0, z / jnp.where(big > 0, big, 1.0), 1.0)
  return optax.projections.projection_l2_sphere(z, jnp.sqrt(z.shape[-1]))


def target_mask(scan, mask=None):
  """Valid target pixels: above ALPHA and finite, unless a mask is given."""
  scan = jnp.asarray(scan, jnp.float32)
  finite = jnp.isfinite(scan)
  if mask is None:
    return finite & (scan > ALPHA)
  return jnp.asarray(mask, bool) & finite


def _search_one(params, apply, target, mask, key, num_steps, lr):
  kz, kn = jax.random.split(key)
  z = project(jax.random.normal(kz, (params.latent_dim,)))
  tx = optax.adam(lr_schedule(num_steps, lr))
  opt = tx.init(z)
  count = jnp.maximum(mask.sum(), 1)
  target = jnp.where(mask, target, 0.0)

  def loss_fn(z):
    x = jnp.tanh(apply(params.variables, z[None])[0, ..., 0])
    return jnp.sum(jnp.where(mask, jnp.abs(x - target), 0.0)) / count

  def body(i, carry):
    z, opt = carry
    t = i / num_steps
    strength = NOISE_SCALE * jnp.maximum(0.0, 1.0 - t / NOISE_RAMP) ** 2
    noise = strength * jax.random.normal(jax.random.fold_in(kn, i), z.shape)
    grad = jax.grad(lambda z: loss_fn(z + noise))(z)
    updates, opt = tx.update(grad, opt, z)
    return project(optax.apply_updates(z, updates)), opt

  z, _ = jax.lax.fori_loop(0, num_steps, body, (z, opt))
  return z, loss_fn(z)


@functools.partial(jax.jit, static_argnames=('num_steps', 'impl'))
def _invert(params, scans, masks, keys, num_steps, lr, impl):
  apply = params.module(impl).apply
  z, loss = jax.vmap(
      lambda t, m, k: _search_one(params, apply, t, m, k, num_steps, lr))(
          scans, masks, keys)
  render_keys = jax.vmap(lambda k: jax.random.fold_in(k, num_steps))(keys)
  out = jax.vmap(lambda zz, k: sampling.generate(params, zz[None], k, impl=impl))(
      z, render_keys)
  out = jax.tree.map(lambda v: v[:, 0], out)
  out.update(latent=z, loss=loss)
  return out


def invert(params: GeneratorParams, scan, mask=None, *, key=None,
           num_steps: int = 1000, lr: float = LR, impl: str | None = None):
  """Reconstructs scans by latent search.

  Args:
    params: a trained generator (see ``load_checkpoint``).
    scan: (H, W) or (B, H, W) normalised inverse depth, ALPHA for drops; NaN
      and inf count as dropped.
    mask: optional bool, same shape: the target pixels to fit (overrides the
      mask inferred from ALPHA).
    key: a PRNG key (default key 0), scan i then using ``fold_in(key, i)``;
      or one key per scan.
    num_steps: optimisation steps (1000 as in the paper).

  Returns:
    dict with ``latent`` (B, d), ``inv_depth`` (x_tilde), ``measurability``,
    ``mask`` and ``scan`` (re-rendered with sampled drops), ``depth``,
    ``valid``, ``points`` (B, H, W, 3) and the final per-scan ``loss``;
    leading batch axis dropped if ``scan`` was 2-D. A scan without any valid
    pixel gets a defined result (the search does not move it) and a warning.
  """
  if not isinstance(num_steps, (int, np.integer)) or num_steps < 1:
    raise ValueError(f'num_steps={num_steps!r}: must be a whole number >= 1')
  sampling.check_params(params)
  scan = jnp.asarray(scan, jnp.float32)
  if scan.ndim not in (2, 3):
    raise ValueError(f'scan of shape {scan.shape}: expected (H, W) or (B, H, W)')
  if not isinstance(scan, jax.core.Tracer):
    finite = np.asarray(scan)[np.isfinite(np.asarray(scan))]
    if finite.size and (finite.min() < ALPHA - 1e-6 or finite.max() > 1.0 + 1e-6):
      raise ValueError(
          f'scan values lie in [{finite.min():.4g}, {finite.max():.4g}], outside the '
          'normalised inverse depth [-1, 1] that invert() takes (metres given by '
          'mistake?); encode metric depth with dusty_jax.codec.encode(depth, '
          'params.sensor), which also marks 0 / out-of-range depths as drops')
  single = scan.ndim == 2
  if mask is not None and np.shape(mask) != scan.shape:
    raise ValueError(f'mask of shape {np.shape(mask)} does not match the scan '
                     f'{scan.shape}')
  if single:
    scan = scan[None]
    mask = None if mask is None else jnp.asarray(mask)[None]
  if scan.shape[1:] != params.sensor.shape:
    raise ValueError(f'scan of shape {scan.shape[1:]} does not match the '
                     f'generator\'s sensor {params.sensor.shape}')
  masks = target_mask(scan, mask)
  scans = jnp.where(jnp.isfinite(scan), scan, ALPHA)
  if not isinstance(masks, jax.core.Tracer):
    empty = np.flatnonzero(~np.asarray(masks.any(axis=(1, 2))))
    if empty.size:
      warnings.warn(f'scans {empty.tolist()} have no valid pixel: nothing to '
                    'fit, their result is the initial latent', stacklevel=2)
  key = sampling.as_key(key)
  if key.shape == (len(scans),):
    keys = key
  elif key.shape == ():
    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(len(scans)))
  else:
    raise ValueError(f'key: expected one key or {len(scans)} keys, got shape '
                     f'{key.shape}')
  out = _invert(params, scans, masks, keys, num_steps, lr, impl)
  if single:
    out = jax.tree.map(lambda v: v[0], out)
  return out


def render_drops(params: GeneratorParams, scan, *, key=None,
                 num_samples: int = 1, num_steps: int = 1000,
                 impl: str | None = None):
  """Gives a clean scan (e.g. a simulated one) realistic point-drops.

  Inverts ``scan`` (H, W) or (B, H, W), then samples ``num_samples`` drop
  masks per scan from the fitted measurability, and applies them to the
  scan itself (not to the reconstruction).

  Returns dict: ``measurability`` (B, H, W), ``masks`` and ``scans``
  (num_samples, B, H, W), and ``inversion`` (the full :func:`invert` result).
  """
  scan = jnp.asarray(scan, jnp.float32)
  single = scan.ndim == 2
  batch = scan[None] if single else scan
  key = jax.random.key(0) if key is None else key
  k_inv, k_mask = jax.random.split(key)
  rec = invert(params, batch, key=k_inv, num_steps=num_steps, impl=impl)
  p = rec['measurability']
  u = jax.random.uniform(k_mask, (num_samples,) + p.shape)
  masks = (u < p).astype(jnp.float32)
  scans = jnp.where(masks > 0, jnp.where(jnp.isfinite(batch), batch, ALPHA), ALPHA)
  out = {'measurability': p, 'masks': masks, 'scans': scans, 'inversion': rec}
  if single:
    out = {'measurability': p[0], 'masks': masks[:, 0], 'scans': scans[:, 0],
           'inversion': jax.tree.map(lambda v: v[0], rec)}
  return out
