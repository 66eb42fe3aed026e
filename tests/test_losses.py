"""GAN losses and R1 against independent formulas, identities and extremes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dusty_jax import losses, models
from dusty_jax.sensor import tiny_sensor

BIG = 1e4  # logits far past where sigmoid saturates in float32.


def _neg_log_sigmoid(x):
  """-log(sigmoid(x)) in float64, straight from the definition."""
  x = np.asarray(x, np.float64)
  return -np.log(1.0 / (1.0 + np.exp(-x)))


def _neg_log_one_minus_sigmoid(x):
  """-log(1 - sigmoid(x)) in float64, straight from the definition."""
  x = np.asarray(x, np.float64)
  return -np.log(1.0 - 1.0 / (1.0 + np.exp(-x)))


# ----------------------------------------------------------------- R1 penalty


def test_r1_of_linear_discriminator_is_squared_norm_of_w():
  rng = np.random.default_rng(0)
  w = jnp.asarray(rng.normal(size=(4, 6)), jnp.float32)
  expected = float(np.sum(np.asarray(w, np.float64) ** 2))
  for b, scale in ((0.0, 1.0), (3.7, 100.0), (-2.0, 1e-3)):
    x = jnp.asarray(scale * rng.normal(size=(5, 4, 6)), jnp.float32)
    d_fn = lambda x, b=b: jnp.sum(x * w, axis=(1, 2)) + b
    np.testing.assert_allclose(float(losses.r1_penalty(d_fn, x)), expected,
                               rtol=1e-5)


def test_r1_of_quadratic_discriminator_matches_hand_gradient():
  # D(x) = 0.5 x^T A x + <c, sin(x)>, per sample on flattened (3, 4) scans:
  # grad = A x + c * cos(x), A symmetric.
  rng = np.random.default_rng(1)
  n = 12
  m = rng.normal(size=(n, n))
  a = (m + m.T) / 2
  c = rng.normal(size=n)
  x = rng.normal(size=(7, 3, 4))

  def d_fn(x):
    flat = x.reshape(x.shape[0], -1)
    quad = 0.5 * jnp.einsum('bi,ij,bj->b', flat, jnp.asarray(a, jnp.float32), flat)
    return quad + jnp.sin(flat) @ jnp.asarray(c, jnp.float32)

  flat = x.reshape(7, n)
  grad = flat @ a + c * np.cos(flat)
  per_sample = np.sum(grad ** 2, axis=1)
  got = losses.r1_penalty(d_fn, jnp.asarray(x, jnp.float32))
  np.testing.assert_allclose(float(got), per_sample.mean(), rtol=1e-5)
  # A batch's penalty is the mean of each scan's penalty alone.
  alone = [float(losses.r1_penalty(d_fn, jnp.asarray(x[i:i + 1], jnp.float32)))
           for i in range(7)]
  np.testing.assert_allclose(alone, per_sample, rtol=1e-5)


def test_r1_of_constant_discriminator_is_zero():
  x = jnp.ones((3, 2, 2))
  assert float(losses.r1_penalty(lambda x: jnp.zeros(x.shape[0]) + 5.0, x)) == 0.0


def test_r1_through_discriminator_matches_finite_differences():
  """R1 of the real discriminator vs. a central-difference gradient (float64)."""
  sensor = tiny_sensor(16, 16)
  h, w = sensor.shape
  with jax.enable_x64(True):
    d = models.Discriminator(sensor, ch_base=2, ch_max=4)
    x = jax.random.uniform(jax.random.key(0), (2, h, w), jnp.float64, -1, 1)
    # Non-zero biases so the leaky units are not all cut at the same place.
    params = jax.jit(lambda k, x: jax.tree.map(
        lambda p: p.astype(jnp.float64) + 0.1 * jax.random.normal(
            jax.random.key(2), p.shape, jnp.float64), d.init(k, x)))(jax.random.key(1), x)
    d_fn = jax.jit(lambda x: d.apply(params, x))
    got = float(jax.jit(lambda x: losses.r1_penalty(d_fn, x))(x))

    eps = 1e-5
    basis = np.eye(h * w).reshape(h * w, h, w)
    fd = []
    for xb in np.asarray(x):  # one scan at a time: every pixel perturbed both ways.
      plus = d_fn(xb[None] + eps * basis)
      minus = d_fn(xb[None] - eps * basis)
      fd.append((np.asarray(plus) - np.asarray(minus)) / (2 * eps))
    fd = np.stack(fd)
  assert got > 0
  # Only a pixel whose +-eps crosses a leaky-ReLU kink can disagree; the sum
  # over 256 pixels barely moves.
  np.testing.assert_allclose(got, np.mean(np.sum(fd ** 2, axis=1)), rtol=1e-4)


# ------------------------------------------------------------ d_loss, g_loss


def test_d_loss_and_g_loss_match_numpy_definitions():
  rng = np.random.default_rng(2)
  real = rng.normal(scale=3.0, size=16).astype(np.float32)
  fake = rng.normal(scale=3.0, size=16).astype(np.float32)
  expected_d = _neg_log_sigmoid(real).mean() + _neg_log_one_minus_sigmoid(fake).mean()
  np.testing.assert_allclose(float(losses.d_loss(real, fake)), expected_d, rtol=1e-6)
  np.testing.assert_allclose(float(losses.g_loss(fake)),
                             _neg_log_sigmoid(fake).mean(), rtol=1e-6)
  # At logits 0 the discriminator is undecided: log 2 each term.
  zeros = jnp.zeros(4)
  np.testing.assert_allclose(float(losses.d_loss(zeros, zeros)), 2 * np.log(2), rtol=1e-6)
  np.testing.assert_allclose(float(losses.g_loss(zeros)), np.log(2), rtol=1e-6)


def test_loss_gradients_match_sigmoid():
  # d/dr softplus(-r) = -sigmoid(-r); d/df softplus(f) = sigmoid(f); mean over n.
  rng = np.random.default_rng(3)
  real = rng.normal(scale=2.0, size=8).astype(np.float32)
  fake = rng.normal(scale=2.0, size=8).astype(np.float32)
  sig = lambda v: 1.0 / (1.0 + np.exp(-np.asarray(v, np.float64)))
  gr, gf = jax.grad(losses.d_loss, argnums=(0, 1))(real, fake)
  np.testing.assert_allclose(gr, -sig(-real) / 8, rtol=1e-5, atol=1e-8)
  np.testing.assert_allclose(gf, sig(fake) / 8, rtol=1e-5, atol=1e-8)
  np.testing.assert_allclose(jax.grad(losses.g_loss)(fake), -sig(-fake) / 8,
                             rtol=1e-5, atol=1e-8)


def test_d_loss_identities():
  rng = np.random.default_rng(4)
  real = jnp.asarray(rng.normal(scale=5.0, size=32), jnp.float32)
  fake = jnp.asarray(rng.normal(scale=5.0, size=32), jnp.float32)
  # Fake logits f are real logits -f: d_loss(r, f) = g_loss(r) + g_loss(-f).
  np.testing.assert_allclose(float(losses.d_loss(real, fake)),
                             float(losses.g_loss(real) + losses.g_loss(-fake)),
                             rtol=1e-6)
  # softplus(x) - softplus(-x) = x: swapping the sign of every logit shifts the
  # loss by mean(fake) - mean(real).
  diff = losses.d_loss(real, fake) - losses.d_loss(-real, -fake)
  np.testing.assert_allclose(float(diff), float(fake.mean() - real.mean()),
                             rtol=1e-5, atol=1e-5)
  # Swapping which batch is real and which fake, with signs flipped, is the
  # same discriminator problem.
  np.testing.assert_allclose(float(losses.d_loss(real, fake)),
                             float(losses.d_loss(-fake, -real)), rtol=1e-6)


@pytest.mark.parametrize('sign', [1.0, -1.0])
def test_losses_at_extreme_logits(sign):
  big = jnp.full((3,), sign * BIG, jnp.float32)
  # sign=+1: a perfect discriminator (real +BIG, fake -BIG) has loss 0 and the
  # fooled generator pays BIG per sample; sign=-1 the other way round.
  d = losses.d_loss(big, -big)
  g = losses.g_loss(-big)
  expected_d = 0.0 if sign > 0 else 2 * BIG
  expected_g = BIG if sign > 0 else 0.0
  np.testing.assert_allclose(float(d), expected_d, rtol=1e-6)
  np.testing.assert_allclose(float(g), expected_g, rtol=1e-6)
  gr, gf = jax.grad(losses.d_loss, argnums=(0, 1))(big, -big)
  gg = jax.grad(losses.g_loss)(-big)
  for grad in (gr, gf, gg):
    assert np.isfinite(np.asarray(grad)).all()
  # Saturated sigmoids: gradients exactly 0 or +-1/n, never NaN.
  n = 3
  np.testing.assert_allclose(gr, (0.0 if sign > 0 else -1.0 / n) * np.ones(n), atol=1e-7)
  np.testing.assert_allclose(gf, (0.0 if sign > 0 else 1.0 / n) * np.ones(n), atol=1e-7)
  np.testing.assert_allclose(gg, (-1.0 / n if sign > 0 else 0.0) * np.ones(n), atol=1e-7)
