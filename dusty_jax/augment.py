"""DiffAugment for range images: brightness, contrast, translation, cutout.

Applied with the same policy to real and generated scans before the
discriminator (Zhao et al. 2020, as adapted by the DUSty authors). The
translation wraps around horizontally (the scan is a cylinder) and fills
vertically with the point-drop constant; the cutout wraps around too.
Colour saturation is the identity on one channel and is left out.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from dusty_jax.projection import ALPHA

POLICY = ('brightness', 'contrast', 'translation', 'cutout')


def brightness(key, x, band=0.5):
  return x + jax.random.uniform(key, (x.shape[0], 1, 1), minval=-band, maxval=band)


def contrast(key, x, band=0.5):
  mean = x.mean(axis=(1, 2), keepdims=True)
  f = jax.random.uniform(key, (x.shape[0], 1, 1), minval=1 - band, maxval=1 + band)
  return mean + (x - mean) * f


def translation(key, x, ratio=1.0 / 8.0):
  b, h, w = x.shape
  sh, sw = int(h * ratio / 2 + 0.5), int(w * ratio / 2 + 0.5)
  kh, kw = jax.random.split(key)
  dy = jax.random.randint(kh, (b,), -sh, sh + 1)
  dx = jax.random.randint(kw, (b,), -sw, sw + 1)
  rows = jnp.arange(h)[None, :] - dy[:, None]          # (B, H) source rows.
  cols = jnp.mod(jnp.arange(w)[None, :] - dx[:, None], w)  # (B, W), wrapped.
  inside = (rows >= 0) & (rows < h)
  y = jnp.take_along_axis(x, jnp.clip(rows, 0, h - 1)[:, :, None], axis=1)
  y = jnp.take_along_axis(y, cols[:, None, :], axis=2)
  return jnp.where(inside[:, :, None], y, ALPHA)


def cutout(key, x, ratio=0.5):
  b, h, w = x.shape
  ch, cw = int(h * ratio + 0.5), int(w * ratio + 0.5)
  ky, kx = jax.random.split(key)
  cy = jax.random.randint(ky, (b, 1, 1), 0, h)
  cx = jax.random.randint(kx, (b, 1, 1), 0, w)
  dy = jnp.arange(h)[None, :, None] - cy
  dx = jnp.mod(jnp.arange(w)[None, None, :] - cx + w // 2, w) - w // 2
  cut = (jnp.abs(dy) <= ch // 2) & (jnp.abs(dx) <= cw // 2)
  return jnp.where(cut, 0.0, x)


FNS = {'brightness': brightness, 'contrast': contrast,
       'translation': translation, 'cutout': cutout}


def diff_augment(key, x, policy=POLICY):
  """Applies each op of ``policy`` in turn to (B, H, W) scans."""
  for name, k in zip(policy, jax.random.split(key, max(len(policy), 1))):
    if name not in FNS:
      raise ValueError(f'unknown augmentation {name!r}; known: {sorted(FNS)}')
    x = FNS[name](k, x)
  return x


def per_example(keys, x, policy=POLICY):
  """diff_augment with one key per example (B keys for B scans)."""
  return jax.vmap(lambda k, xi: diff_augment(k, xi[None], policy)[0])(keys, x)
