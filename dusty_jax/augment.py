"""DiffAugment for range images: brightness, contrast, translation, cutout.

Applied with the same policy to real and generated scans before the
discriminator (Zhao et al. 2020, as adapted by the DUSty authors). Colour
saturation is the identity on one channel and is left out.

Two styles (``style``), differing only in the distributions drawn:
  * ``'authors'`` (default): what the authors' code actually draws. Their
    ``factor.bernoulli_(p) * factor.uniform_(-1, 1)`` multiplies a tensor by
    itself after both in-place fills, so brightness adds 0.5 u^2 (u ~ U(-1, 1):
    in [0, 0.5], mean 1/6) and contrast scales by 1 + 0.5 u^2 (in [1, 1.5]).
    Translation fills rows shifted in from outside with 0 and wraps columns
    modulo W - 1 (column W - 1 is never read). Cutout zeroes a window of
    round(H/2) x round(W/2) (32 x 128 at 64 x 256) whose centre is uniform
    over [0, H] x [0, W], clamped at the borders, not wrapped.
  * ``'symmetric'``: DiffAugment's intended distributions on the cylinder:
    brightness U(-0.5, 0.5), contrast U(0.5, 1.5), translation filling with
    the point-drop constant and wrapping modulo W, and a cutout of
    (2 round(H/4) + 1) x (2 round(W/4) + 1) that wraps around horizontally.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from dusty_jax import configs
from dusty_jax.codec import ALPHA

POLICY = ('brightness', 'contrast', 'translation', 'cutout')
STYLES = ('authors', 'symmetric')


def _factor(key, b, style):
  """(B, 1, 1) draws: U(-1, 1) ('symmetric') or u^2, u ~ U(-1, 1) ('authors')."""
  u = jax.random.uniform(key, (b, 1, 1), minval=-1.0, maxval=1.0)
  return u * u if style == 'authors' else u


def brightness(key, x, style='authors', band=0.5):
  return x + band * _factor(key, x.shape[0], style)


def contrast(key, x, style='authors', band=0.5):
  mean = x.mean(axis=(1, 2), keepdims=True)
  return mean + (x - mean) * (1.0 + band * _factor(key, x.shape[0], style))


def translation(key, x, style='authors', ratio=1.0 / 8.0):
  b, h, w = x.shape
  sh, sw = int(h * ratio / 2 + 0.5), int(w * ratio / 2 + 0.5)
  kh, kw = jax.random.split(key)
  dy = jax.random.randint(kh, (b,), -sh, sh + 1)
  dx = jax.random.randint(kw, (b,), -sw, sw + 1)
  period, fill = (w - 1, 0.0) if style == 'authors' else (w, ALPHA)
  rows = jnp.arange(h)[None, :] + dy[:, None]                   # (B, H) source rows.
  cols = jnp.mod(jnp.arange(w)[None, :] + dx[:, None], period)  # (B, W), wrapped.
  inside = (rows >= 0) & (rows < h)
  y = jnp.take_along_axis(x, jnp.clip(rows, 0, h - 1)[:, :, None], axis=1)
  y = jnp.take_along_axis(y, cols[:, None, :], axis=2)
  return jnp.where(inside[:, :, None], y, fill)


def cutout(key, x, style='authors', ratio=0.5):
  b, h, w = x.shape
  ch, cw = int(h * ratio + 0.5), int(w * ratio + 0.5)
  ky, kx = jax.random.split(key)
  dy_ = jnp.arange(h)[None, :, None]
  dx_ = jnp.arange(w)[None, None, :]
  if style == 'authors':
    # Window rows [cy - ch//2, cy - ch//2 + ch), cy in [0, H + 1 - ch % 2).
    cy = jax.random.randint(ky, (b, 1, 1), 0, h + 1 - ch % 2) - ch // 2
    cx = jax.random.randint(kx, (b, 1, 1), 0, w + 1 - cw % 2) - cw // 2
    cut = (dy_ >= cy) & (dy_ < cy + ch) & (dx_ >= cx) & (dx_ < cx + cw)
  else:
    cy = jax.random.randint(ky, (b, 1, 1), 0, h)
    cx = jax.random.randint(kx, (b, 1, 1), 0, w)
    dx = jnp.mod(dx_ - cx + w // 2, w) - w // 2
    cut = (jnp.abs(dy_ - cy) <= ch // 2) & (jnp.abs(dx) <= cw // 2)
  return jnp.where(cut, 0.0, x)


FNS = {'brightness': brightness, 'contrast': contrast,
       'translation': translation, 'cutout': cutout}


def check(policy, style):
  if style not in STYLES:
    raise ValueError(f'unknown augmentation style {style!r}; known: {list(STYLES)}')
  for name in policy:
    if name not in FNS:
      raise ValueError(f'unknown augmentation {name!r}; known: {sorted(FNS)}')


def check_config(config):
  """configs.validate's check of a config's augmentation fields, here
  beside the names it checks; raises configs.ConfigError naming the field."""
  def need(ok, field, why):
    if not ok:
      raise configs.ConfigError(f'config field {field}={config[field]!r}: {why}')
  need(config.augment_style in STYLES, 'augment_style',
       f"must be one of {', '.join(map(repr, STYLES))}")
  unknown = [p for p in config.augment.split(',') if p and p not in FNS]
  need(not unknown, 'augment', unknown and f'{unknown[0]!r} is no augmentation; give a '
       f"comma-separated list of {', '.join(FNS)} ('' for none)")


def diff_augment(key, x, policy=POLICY, style='authors'):
  """Applies each op of ``policy`` in turn to (B, H, W) scans."""
  check(policy, style)
  for name, k in zip(policy, jax.random.split(key, max(len(policy), 1))):
    x = FNS[name](k, x, style)
  return x


def per_example(keys, x, policy=POLICY, style='authors'):
  """diff_augment with one key per example (B keys for B scans)."""
  return jax.vmap(lambda k, xi: diff_augment(k, xi[None], policy, style)[0])(keys, x)
