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

from dusty_jax import codec, encoder as encoder_lib, errors, pretrained, sampling
from dusty_jax.codec import ALPHA
from dusty_jax.generator import GeneratorParams

LR = 0.1
RAMP_UP = 0.05
RAMP_DOWN = 0.25
NOISE_SCALE = 0.05
NOISE_RAMP = 0.75


def lr_schedule(num_steps, lr: float = LR):
  """StyleGAN2's projector schedule: linear ramp-up, flat, cosine ramp-down.

  Over progress t = step / num_steps: lr * min(1, t / RAMP_UP) times
  0.5 - 0.5 cos(pi min(1, (1 - t) / RAMP_DOWN)). The boundaries may fall
  between steps; the pieces meet at lr, so that is harmless.

  ``num_steps`` may be traced, so that invert() compiles once for every step
  count: the pieces are optax.linear_schedule, constant_schedule and
  cosine_decay_schedule joined as optax.join_schedules joins them, written
  out because those check their step counts in Python.
  """
  up = RAMP_UP * num_steps
  down = RAMP_DOWN * num_steps

  def schedule(step):
    ramp = lr - lr * (1 - jnp.clip(step, 0, up) / up)  # linear_schedule(0, lr, up)
    cosine = lr * (0.5 * (1 + jnp.cos(jnp.pi * jnp.minimum(step - (num_steps - down), down)
                                      / down)))  # cosine_decay_schedule(lr, down)
    return jnp.where(step < num_steps - down, jnp.where(step < up, ramp, lr), cosine)

  return schedule


project = encoder_lib.project  # onto the latent sphere of radius sqrt(d)


def target_mask(scan, mask=None):
  """Valid target pixels: above ALPHA and finite, unless a mask is given."""
  scan = jnp.asarray(scan, jnp.float32)
  finite = jnp.isfinite(scan)
  if mask is None:
    return finite & (scan > ALPHA)
  return jnp.asarray(mask, bool) & finite


def objective(x_tilde, target, mask):
  """What the search minimises: the mean L1 distance between x_tilde and the
  target over the mask's pixels (0 where the mask is empty).

  Any function of this signature (one scan's (H, W) arrays -> a scalar) can
  be passed to :func:`invert` as ``loss``.
  """
  count = jnp.maximum(mask.sum(), 1)
  return jnp.sum(jnp.where(mask, jnp.abs(x_tilde - target), 0.0)) / count


def random_start(params, scans, masks, keys):
  """The authors' start: per scan, z ~ N(0, I) from the first half of the
  scan's key, projected onto the sphere."""
  del scans, masks
  return jax.vmap(lambda k: project(jax.random.normal(
      jax.random.split(k)[0], (params.latent_dim,))))(keys)


def encoder_start(params, scans, masks, keys):
  """The encoder's answer (encoder.py), from the scan's valid target pixels."""
  del keys
  return encoder_lib.encode(params, jnp.where(masks, scans, ALPHA))


# How a search can start, by name: each maps (params, scans (B, H, W), masks,
# keys (B,)) to (B, d) latents on the sphere, traced inside invert's jit.
# invert(init=NAME) looks the name up here; a new start is one more entry.
STARTS = {'random': random_start, 'encoder': encoder_start}


def scan_loss(params, apply, z, target, mask, loss=objective):
  """What the search minimises for one scan: ``loss`` of the generator's
  x_tilde at the latent ``z`` (d,) against ``target`` on ``mask`` (H, W);
  ``apply`` is ``params.module(impl).apply``."""
  raw = apply(params.variables, z[None])
  return loss(params.variant.decode_inv_depth(raw)[0], target, mask)


def _search_one(params, apply, target, mask, z, key, num_steps, lr, loss):
  """One scan's search of ``num_steps`` (traced: a while loop) steps."""
  kn = jax.random.split(key)[1]
  tx = optax.adam(lr_schedule(jnp.maximum(num_steps, 1), lr))
  opt = tx.init(z)
  target = jnp.where(mask, target, 0.0)
  loss_fn = lambda z: scan_loss(params, apply, z, target, mask, loss)

  def body(i, carry):
    z, opt = carry
    t = i / num_steps
    strength = NOISE_SCALE * jnp.maximum(0.0, 1.0 - t / NOISE_RAMP) ** 2
    noise = strength * jax.random.normal(jax.random.fold_in(kn, i), z.shape)
    grad = jax.grad(lambda z: loss_fn(z + noise))(z)
    updates, opt = tx.update(grad, opt, z)
    return project(optax.apply_updates(z, updates)), opt

  # 0 steps: the start is the answer.
  z, _ = jax.lax.fori_loop(0, num_steps, body, (z, opt))
  return z, loss_fn(z)


@functools.partial(jax.jit, static_argnames=('start',))
def _start(params, scan, mask, key, z0, start):
  """What a search starts from: the target scans (drops at ALPHA), their
  masks, one key per scan and the starting latents (``start`` a name in
  STARTS, or None for the given ``z0``, projected). One small program apart
  from the search, so that a new start compiles only this."""
  masks = target_mask(scan, mask)
  scans = jnp.where(jnp.isfinite(scan), scan, ALPHA)
  if key.ndim == 0:
    key = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(len(scans)))
  z0 = project(z0) if start is None else STARTS[start](params, scans, masks, key)
  return scans, masks, key, z0


@functools.partial(jax.jit, static_argnames=('impl', 'loss'))
def _search(params, scans, masks, z0, keys, num_steps, lr, impl, loss):
  """The searches from ``z0`` and their re-rendered results. ``num_steps``
  and ``lr`` are traced: one compilation serves every step count."""
  apply = params.module(impl).apply
  z, final = jax.vmap(
      lambda t, m, z, k: _search_one(params, apply, t, m, z, k, num_steps, lr, loss))(
          scans, masks, z0, keys)
  render_keys = jax.vmap(lambda k: jax.random.fold_in(k, num_steps))(keys)
  out = jax.vmap(lambda zz, k: sampling.generate(params, zz[None], k, impl=impl))(
      z, render_keys)
  out = jax.tree.map(lambda v: v[:, 0], out)
  out.update(latent=z, loss=final)
  return out


def _check_init(params, init, num_scans):
  """(start name, None) or (None, given latents) of invert's ``init``."""
  if isinstance(init, str):
    if init not in STARTS:
      raise ValueError(f'init={init!r}: known starts are {sorted(STARTS)}, or '
                       'given latents (B, latent_dim)')
    if init == 'encoder':
      encoder_lib.check_has_encoder(params, f'generator {params.model!r}',
                                    pretrained.with_encoder())
    return init, None
  z = jnp.asarray(errors.check_finite(init, 'init latents'), jnp.float32)
  want = (num_scans, params.latent_dim)
  if z.shape != want:
    raise ValueError(f'init latents of shape {z.shape}: expected {want} (one '
                     'latent of the generator\'s latent_dim per scan)')
  return None, z


def _warn_if_not_encoded(scans: np.ndarray, single: bool):
  """Warns about scans that lie in [0, 1] with no drop: depth / max_depth
  (or another [0, 1] normalisation) given for normalised inverse depth. An
  encoded scan has its returns beyond about twice the minimum range below 0
  and its drops at ALPHA = -1; a real or simulated scan has both."""
  suspect = [i for i, x in enumerate(scans)
             if np.isfinite(x).any() and not (x[np.isfinite(x)] < 0).any()]
  if suspect:
    which = 'the scan has' if single else f'scans {suspect} have'
    warnings.warn(
        f'{which} no value below 0 and no drop (-1): not normalised inverse depth '
        'as invert() takes, where far returns lie below 0 and drops at -1. Given '
        'depth / max_depth (or other [0, 1] values) by mistake? Encode metric '
        'depth with dusty_jax.codec.encode(depth, params.sensor)', stacklevel=4)


def _warn_if_empty(scans: np.ndarray, masks: np.ndarray | None):
  """Warns about scans without a valid target pixel (target_mask, in numpy)."""
  finite = np.isfinite(scans)
  valid = finite & (scans > ALPHA) if masks is None else masks.astype(bool) & finite
  empty = np.flatnonzero(~valid.any(axis=(1, 2)))
  if empty.size:
    warnings.warn(f'scans {empty.tolist()} have no valid pixel: nothing to '
                  'fit, their result is the initial latent', stacklevel=4)


def _check_scans(params, scan, mask):
  """invert's (scan (B, H, W) float32, mask (B, H, W) or None, single) from
  its arguments, or the error naming what is wrong with them."""
  scan = jnp.asarray(codec.check_precision(scan, 'scan'), jnp.float32)
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
  given = scan.shape
  if mask is not None and np.shape(mask) != scan.shape:
    raise ValueError(f'mask of shape {np.shape(mask)} does not match the scan '
                     f'{scan.shape}')
  if single:
    scan = scan[None]
    mask = None if mask is None else jnp.asarray(mask)[None]
  if scan.shape[1:] != params.sensor.shape:
    hw = tuple(params.sensor.shape)
    raise ValueError(f'scan of shape {given} does not match the generator\'s sensor '
                     f'{hw}: expected {hw} or (B,) + {hw}')
  if not isinstance(scan, jax.core.Tracer):
    _warn_if_not_encoded(np.asarray(scan), single)
    if not isinstance(mask, jax.core.Tracer):
      _warn_if_empty(np.asarray(scan), None if mask is None else np.asarray(mask))
  return scan, mask, single


def invert(params: GeneratorParams, scan, mask=None, *, key=None,
           num_steps: int = 1000, lr: float = LR, impl: str | None = None,
           init='random', loss=objective):
  """Reconstructs scans by latent search.

  Args:
    params: a trained generator (see ``load_checkpoint``).
    scan: (H, W) or (B, H, W) normalised inverse depth, ALPHA for drops; NaN
      and inf count as dropped; float16 and bfloat16 are refused
      (codec.check_precision).
    mask: optional bool, same shape: the target pixels to fit (overrides the
      mask inferred from ALPHA).
    key: a PRNG key (default key 0), scan i then using ``fold_in(key, i)``;
      or one key per scan.
    num_steps: optimisation steps (1000 as in the paper; at most 2**31 - 1,
      an int32 once compiled); 0 returns the
      start itself (with ``init='encoder'``: the encoder's answer alone).
    init: where the search starts: a name in ``STARTS`` (``'random'``, the
      authors' start, drawn from each scan's key; ``'encoder'``, the answer
      of the generator's encoder, see encoder.py), or given latents (B, d)
      (one per scan, (d,) for a 2-D scan), projected onto the sphere: any
      finite scale; NaN or inf is refused (errors.InputError).
    loss: the objective ``loss(x_tilde, target, mask) -> scalar`` of one
      scan (default :func:`objective`, the authors' masked L1); a hashable
      function, as jit keys its compilation on it.
    lr: Adam's peak learning rate (a finite number > 0).

  Returns:
    dict with ``latent`` (B, d), ``inv_depth`` (x_tilde), ``measurability``,
    ``mask`` and ``scan`` (re-rendered with sampled drops), ``depth``,
    ``valid``, ``points`` (B, H, W, 3) and the final per-scan ``loss``;
    leading batch axis dropped if ``scan`` was 2-D. A scan without any valid
    pixel gets a defined result (the search does not move it) and a warning;
    so does a scan with no value below 0 and no drop (not encoded). A batch
    of 0 scans gives results with a leading axis of 0 (as numpy: empty in,
    empty out).
  """
  num_steps = errors.check_count(num_steps, 'num_steps')
  if not isinstance(lr, jax.core.Tracer) and not (
      np.ndim(lr) == 0 and np.isfinite(lr) and lr > 0):
    raise ValueError(f'lr={lr!r}: the learning rate must be a finite number > 0')
  sampling.check_params(params)
  params = sampling.full_precision(params)
  scan, mask, single = _check_scans(params, scan, mask)
  key = sampling.as_key(key)
  if key.shape not in ((), (len(scan),)):
    raise ValueError(f'key: expected one key or {len(scan)} keys, got shape '
                     f'{key.shape}')
  if single and not isinstance(init, str):
    init = jnp.asarray(init)[None]
  start, z0 = _check_init(params, init, len(scan))
  if mask is not None:
    mask = jnp.asarray(mask)
  scans, masks, keys, z0 = _start(params, scan, mask, key, z0, start)
  out = _search(params, scans, masks, z0, keys, np.int32(num_steps), lr, impl, loss)
  return _first(out) if single else out


@jax.jit
def _first(out):
  """The results of a batch of one, without the batch axis."""
  return jax.tree.map(lambda v: v[0], out)


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
  num_samples = errors.check_count(num_samples, 'num_samples')
  scan = jnp.asarray(scan, jnp.float32)
  key = sampling.as_key(key)
  k_inv, k_mask = jax.random.split(key)
  rec = invert(params, scan, key=k_inv, num_steps=num_steps, impl=impl)
  p = rec['measurability']  # (H, W) for a 2-D scan, as each of rec's arrays
  u = jax.random.uniform(k_mask, (num_samples,) + p.shape)
  masks = (u < p).astype(jnp.float32)
  scans = jnp.where(masks > 0, jnp.where(jnp.isfinite(scan), scan, ALPHA), ALPHA)
  return {'measurability': p, 'masks': masks, 'scans': scans, 'inversion': rec}
