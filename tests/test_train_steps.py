"""The pure pieces of a train step, each alone: d_step, g_step, ema_update."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from dusty_jax import augment, codec, drops, losses, trainer
from dusty_jax.sensor import tiny_sensor
from train_helpers import STUDY, tiny_config


def _setup(**overrides):
  config = tiny_config(**overrides)
  sensor = tiny_sensor(config.sensor.height, config.sensor.width)
  setup = trainer.make_setup(config, sensor)
  state = trainer.init_state(setup, jax.random.key(0))
  return config, setup, state


def _adam(tx, grads, opt, params):
  """(params, opt state) after one update of ``tx``, compiled (eager optax
  compiles one small program per leaf shape and op)."""
  def update(g, o, p):
    updates, o = tx.update(g, o, p)
    return optax.apply_updates(p, updates), o
  return jax.jit(update)(grads, opt, params)


def _close(a, b, rtol=1e-5, atol=1e-6):
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
    np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol)


N = 2  # examples per batch


def _batch(setup, seed=0):
  rng = np.random.default_rng(seed)
  return jnp.asarray(rng.uniform(-1, 1, (N,) + setup.sensor.shape), jnp.float32)


def _d_step(setup, state, real, fake, keys, r1_now=True):
  # r1_now traced, as in train_step: one compilation serves both values.
  step = jax.jit(lambda dp, do, r, f, k, now: trainer.d_step(setup, dp, do, r, f, k, now))
  return step(state.d_params, state.d_opt, real, fake, keys, jnp.asarray(r1_now))


def _fakes(setup, n=N):
  z = jax.random.normal(jax.random.key(5), (n, setup.settings.latent_dim))
  keys = jax.random.split(jax.random.key(6), n)
  return z, keys


def _keys(n, seed):
  return jax.random.split(jax.random.key(seed), n)


@pytest.mark.parametrize('r1_gamma', [0.0, 2.0])
def test_d_step_is_adam_on_the_gan_loss_plus_r1(r1_gamma):
  """Without augmentation: D's update is Adam on d_loss + gamma/2 R1, both
  computed here from the discriminator directly."""
  _, setup, state = _setup(augment='', r1_gamma=r1_gamma, r1_every=1)
  real, fake = _batch(setup, 0), _batch(setup, 1)
  keys = (_keys(N, 1), _keys(N, 2))
  d_params, d_opt, m = _d_step(setup, state, real, fake, keys)
  apply = setup.discriminator.apply

  def total(dp):
    adv = losses.d_loss(apply(dp, real), apply(dp, fake))
    g = jax.grad(lambda x: apply(dp, x).sum())(real)
    return adv + 0.5 * r1_gamma * jnp.mean(jnp.sum(g ** 2, axis=(1, 2)))

  grads = jax.jit(jax.grad(total))(state.d_params)
  want, want_opt = _adam(setup.d_tx, grads, state.d_opt, state.d_params)
  _close(d_params, want)
  _close(d_opt, want_opt)
  adv = jax.jit(lambda dp: losses.d_loss(apply(dp, real), apply(dp, fake)))
  np.testing.assert_allclose(m['loss_d'], adv(state.d_params), rtol=1e-6)
  assert (float(m['r1']) > 0) == (r1_gamma > 0)


def test_lazy_r1_is_off_between_its_steps():
  """With r1_every = 4 a step that skips R1 reports 0 and updates as if
  gamma were 0 (with the same lazily adjusted Adam); one that applies it
  reports the penalty and differs."""
  _, setup, state = _setup(augment='', r1_gamma=1.0, r1_every=4)
  real, fake = _batch(setup, 0), _batch(setup, 1)
  keys = (_keys(N, 1), _keys(N, 2))
  off = _d_step(setup, state, real, fake, keys, r1_now=False)
  on = _d_step(setup, state, real, fake, keys, r1_now=True)
  plain = _d_step(setup.replace(r1_gamma=0.0), state, real, fake, keys)
  assert float(off[2]['r1']) == 0.0 and float(on[2]['r1']) > 0
  _close(off[0], plain[0])
  diff = max(float(jnp.abs(a - b).max())
             for a, b in zip(jax.tree.leaves(on[0]), jax.tree.leaves(off[0])))
  assert diff > 1e-6


@pytest.mark.slow
def test_g_step_through_the_vjp_equals_a_fresh_gradient():
  """g_step reuses the forward pass through its VJP; the update must equal
  Adam on the gradient of the non-saturating loss computed from scratch."""
  _, setup, state = _setup()
  z, mask_keys = _fakes(setup)
  aug_keys = _keys(N, 3)
  render = lambda p: trainer.fake_scans(setup, p, z, mask_keys)['scan']

  @jax.jit
  def step(gp, go, dp):
    fake, vjp = jax.vjp(lambda p: trainer.Fake(scan=render(p)), gp)
    return trainer.g_step(setup, gp, go, dp, fake, vjp, aug_keys)

  g_params, g_opt, loss = step(state.g_params, state.g_opt, state.d_params)

  def objective(p):
    x = augment.per_example(aug_keys, render(p), setup.policy, setup.augment_style)
    return losses.g_loss(setup.discriminator.apply(state.d_params, x))

  want_loss, grads = jax.jit(jax.value_and_grad(objective))(state.g_params)
  want, want_opt = _adam(setup.g_tx, grads, state.g_opt, state.g_params)
  np.testing.assert_allclose(loss, want_loss, rtol=1e-6)
  _close(g_params, want)
  _close(g_opt, want_opt)


def test_ema_update_and_decay():
  rng = np.random.default_rng(0)
  ema = {'a': rng.normal(size=(3, 2)).astype(np.float32), 'b': np.float32(1.5)}
  new = {'a': rng.normal(size=(3, 2)).astype(np.float32), 'b': np.float32(-0.5)}
  out = trainer.ema_update(ema, new, 0.75)
  np.testing.assert_allclose(out['a'], 0.75 * ema['a'] + 0.25 * new['a'], rtol=1e-6)
  assert float(out['b']) == pytest.approx(0.75 * 1.5 - 0.25 * 0.5)
  _close(trainer.ema_update(ema, new, 1.0), ema)
  _close(trainer.ema_update(ema, new, 0.0), new)

  config, setup, _ = _setup(ema_rampup=0.0)
  b = config.batch_size
  assert trainer.ema_decay(setup, jnp.int32(7)) == pytest.approx(
      0.5 ** (b / (config.ema_halflife_kimg * 1000)))
  config, setup, _ = _setup(ema_rampup=0.05)
  for step in (0, 10, 10**6):
    halflife = min(config.ema_halflife_kimg * 1000, (step + 1) * b * 0.05)
    assert float(trainer.ema_decay(setup, jnp.int32(step))) == pytest.approx(
        0.5 ** (b / halflife), rel=1e-5)


@pytest.mark.slow
def test_g_step_with_drops_terms_adds_them_to_the_gradient_not_the_loss():
  """With sim-dusty2's options ('dips'), G's update is Adam on the gradient
  of the adversarial loss plus drops.add_penalties, taken through the
  Fake's scan, mask and detached head; the reported loss is the
  adversarial one alone."""
  config = tiny_config()
  config.drops.update(STUDY['DIPS'])
  setup = trainer.make_setup(config, tiny_sensor(config.sensor.height, config.sensor.width))
  state = trainer.init_state(setup, jax.random.key(0), np.linspace(0.5, 0.9, 16))
  assert setup.drops.rate_head_only and setup.drops.dip_weight > 0
  z, mask_keys = _fakes(setup)
  aug_keys = _keys(N, 3)
  x = _batch(setup, 4)
  x = jnp.where(jax.random.uniform(jax.random.key(7), x.shape) < 0.3, codec.ALPHA, x)
  real = (x, (x > codec.ALPHA).astype(x.dtype))

  def render(p):
    out = trainer.fake_scans(setup, p, z, mask_keys, detached_head=True)
    return trainer.Fake(scan=out['scan'], mask=out['mask'], head_keep=out['head_keep'])

  @jax.jit
  def step(gp, go, dp):
    fake, vjp = jax.vjp(render, gp)
    return trainer.g_step(setup, gp, go, dp, fake, vjp, aug_keys, real=real)

  g_params, g_opt, loss = step(state.g_params, state.g_opt, state.d_params)

  def adversarial(p):
    x = augment.per_example(aug_keys, render(p).scan, setup.policy, setup.augment_style)
    return losses.g_loss(setup.discriminator.apply(state.d_params, x))

  def objective(p):
    f = render(p)
    keep = f.head_keep
    return (adversarial(p)
            + 10.0 * drops.dip_penalty(f.scan)
            + 100.0 * drops.ring_depth_rate_penalty(setup.sensor, (f.scan, f.mask), real,
                                                    keep=keep))

  grads = jax.jit(jax.grad(objective))(state.g_params)
  want, _ = _adam(setup.g_tx, grads, state.g_opt, state.g_params)
  np.testing.assert_allclose(loss, jax.jit(adversarial)(state.g_params), rtol=1e-6)
  _close(g_params, want)
  # The terms weigh: without them the update differs.
  plain, _ = _adam(setup.g_tx, jax.jit(jax.grad(adversarial))(state.g_params), state.g_opt,
                   state.g_params)
  assert max(float(jnp.abs(a - b).max()) for a, b in
             zip(jax.tree.leaves(plain), jax.tree.leaves(want))) > 1e-6
