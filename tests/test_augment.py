"""DiffAugment: the authors' distributions and the symmetric alternative."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dusty_jax import augment
from dusty_jax.codec import ALPHA


def _scans(b=64, h=16, w=64, seed=0):
  return jnp.asarray(np.random.default_rng(seed).uniform(-1, 1, (b, h, w)), jnp.float32)


def test_authors_brightness_and_contrast_ranges():
  x = _scans(4096, 2, 4)
  shift = (augment.brightness(jax.random.key(0), x, 'authors') - x)[:, 0, 0]
  assert float(shift.min()) >= 0.0 and float(shift.max()) <= 0.5
  # 0.5 u^2 with u ~ U(-1, 1): mean 1/6.
  assert float(shift.mean()) == pytest.approx(1 / 6, abs=0.01)
  sym = (augment.brightness(jax.random.key(0), x, 'symmetric') - x)[:, 0, 0]
  assert float(sym.min()) < -0.4 and float(sym.max()) > 0.4
  y = augment.contrast(jax.random.key(1), x, 'authors')
  m = x.mean(axis=(1, 2), keepdims=True)
  f = ((y - m) / (x - m))[:, 0, 0]
  assert float(f.min()) >= 1.0 - 1e-4 and float(f.max()) <= 1.5 + 1e-4


def _authors_translation(x, dy, dx):
  """The authors' translation rule: rows from outside filled with 0, columns
  wrapped modulo W - 1 (written independently of augment.py)."""
  b, h, w = x.shape
  y = np.zeros_like(x)
  for i in range(b):
    for r in range(h):
      src = r + dy[i]
      if 0 <= src < h:
        for c in range(w):
          y[i, r, c] = x[i, src, (c + dx[i]) % (w - 1)]
  return y


def test_authors_translation_matches_the_index_rule():
  x = np.asarray(_scans(6, 8, 32))
  key = jax.random.key(3)
  y = np.asarray(augment.translation(key, jnp.asarray(x), 'authors'))
  kh, kw = jax.random.split(key)
  sh, sw = int(8 / 16 + 0.5), int(32 / 16 + 0.5)
  dy = np.asarray(jax.random.randint(kh, (6,), -sh, sh + 1))
  dx = np.asarray(jax.random.randint(kw, (6,), -sw, sw + 1))
  np.testing.assert_array_equal(y, _authors_translation(x, dy, dx))


def test_symmetric_translation_commutes_with_circular_shift():
  """On the cylinder, shifting the input shifts the output (same draws)."""
  x = _scans(8)
  a = jnp.roll(augment.translation(jax.random.key(5), x, 'symmetric'), 7, axis=2)
  b = augment.translation(jax.random.key(5), jnp.roll(x, 7, axis=2), 'symmetric')
  np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  # The fill of rows shifted in is the drop constant.
  y = np.asarray(augment.translation(jax.random.key(6), jnp.zeros((64, 16, 64)) + 0.5,
                                     'symmetric'))
  assert set(np.unique(y)) <= {0.5, ALPHA} and (y == ALPHA).any()


def test_cutout_windows():
  x = jnp.ones((256, 64, 256))
  y = np.asarray(augment.cutout(jax.random.key(0), x, 'authors'))
  cut = y == 0
  rows, cols = cut.any(axis=2).sum(1), cut.any(axis=1).sum(1)
  # 32 x 128 windows, clamped at the borders (never wrapping).
  assert rows.max() == 32 and cols.max() == 128 and rows.min() < 32
  for c in cut:
    nz = np.flatnonzero(c.any(axis=0))
    assert nz.max() - nz.min() + 1 == len(nz)  # contiguous: no wrap
  assert (cut.sum((1, 2)) == rows * cols).all()  # rectangles
  cut = np.asarray(augment.cutout(jax.random.key(0), x, 'symmetric')) == 0
  rows = cut.any(axis=2).sum(1)
  # Horizontally the window wraps around (always 129 columns), vertically it
  # is clipped at the top and bottom rings.
  assert (cut.sum((1, 2)) == rows * 129).all() and rows.max() == 33 and rows.min() < 33
  assert cut[:, :, 0].any() and cut[:, :, -1].any()


def test_unknown_policy_or_style_fails():
  with pytest.raises(ValueError, match='unknown augmentation'):
    augment.diff_augment(jax.random.key(0), _scans(2), ('flip',))
  with pytest.raises(ValueError, match='style'):
    augment.diff_augment(jax.random.key(0), _scans(2), style='fancy')
