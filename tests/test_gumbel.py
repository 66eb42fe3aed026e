"""Straight-through Gumbel-sigmoid and rendering, at the extremes too."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dusty_jax import gumbel, models
from dusty_jax.codec import ALPHA


def test_mask_frequency_matches_sigmoid():
  logits = jnp.array([-3.0, -1.0, 0.0, 0.5, 2.0])
  keys = jax.random.split(jax.random.key(0), 20000)
  masks = jax.vmap(lambda k: gumbel.pixel_mask(k, logits))(keys)
  np.testing.assert_allclose(masks.mean(0), jax.nn.sigmoid(logits), atol=0.012)
  assert set(np.unique(masks).tolist()) <= {0.0, 1.0}


def test_straight_through_gradient_is_soft_gradient():
  logits, noise = jnp.array([0.3, -0.7, 2.0]), jnp.array([0.1, 0.2, -0.4])
  for tau in (1.0, 0.5):
    g_st = jax.grad(lambda l: (gumbel.straight_through(l, noise, tau) * jnp.arange(3.)).sum())(logits)
    g_soft = jax.grad(lambda l: (jax.nn.sigmoid((l + noise) / tau) * jnp.arange(3.)).sum())(logits)
    np.testing.assert_allclose(g_st, g_soft, rtol=1e-6)
  hard = gumbel.straight_through(logits, noise)
  assert hard.tolist() == [1.0, 0.0, 1.0]


@pytest.mark.parametrize('tau', [1.0, 1e-3, 1e-6])
def test_extremes_no_nan(tau):
  logits = jnp.array([-1e4, 1e4, 0.0, -1e4, 1e4])
  u = jnp.array([0.0, 1.0, 0.0, 1.0, 0.5])  # uniform draws exactly 0 and 1.
  noise = gumbel.logistic_from_uniform(u)
  assert np.isfinite(np.asarray(noise)).all()
  f = lambda l: gumbel.straight_through(l, noise, tau)
  m = f(logits)
  assert m.tolist()[:2] == [0.0, 1.0]
  g = jax.jacobian(lambda l: f(l).sum())(logits)
  assert np.isfinite(np.asarray(g)).all()


def test_always_dropped_pixel_renders_alpha_with_finite_grads():
  raw = jnp.zeros((2, 4, 8, 3)).at[..., 1].set(-1e4)  # measurability ~ 0.
  for model in ('dusty1', 'dusty2'):
    out = models.get_variant(model).compose(raw, jax.random.key(0))
    assert (out['scan'] == ALPHA).all() and (out['mask'] == 0).all()
    g = jax.grad(lambda r: models.get_variant(model).compose(r, jax.random.key(0))['scan'].sum())(raw)
    assert np.isfinite(np.asarray(g)).all()


def test_image_level_noise_shared_and_off_at_test():
  logits = jnp.zeros((64, 4, 8))
  m = gumbel.image_mask(jax.random.key(1), logits)
  per_image = m.reshape(64, -1)
  assert (per_image.min(1) == per_image.max(1)).all()  # one draw per image.
  assert 0 < float(per_image[:, 0].mean()) < 1
  det = gumbel.image_mask(jax.random.key(1), logits + 0.1, train=False)
  assert (det == 1).all()
  assert (gumbel.image_mask(jax.random.key(1), logits - 0.1, train=False) == 0).all()


def test_dusty2_multiplies_masks_and_measurability():
  raw = jnp.zeros((1, 2, 2, 3)).at[..., 1].set(10.0).at[..., 2].set(-10.0)
  out = models.get_variant('dusty2').compose(raw, jax.random.key(0), train=False)
  assert (out['mask'] == 0).all()  # image-level says drop: everything dropped.
  assert (models.get_variant('dusty2').measurability(out['logit']) == 0).all()
  base = models.get_variant('baseline').compose(raw, jax.random.key(0))
  np.testing.assert_allclose(base['scan'], jnp.tanh(raw[..., 0]))
