"""GAN training: the train state, pure step functions, and the loop.

One step is ``train_step(state, batch, key) -> (state, metrics)``, written
once per device with the named axis ``'data'`` (gradients and metrics are
``pmean``-ed over it) and wrapped for the devices at hand in parallel.py.

A step updates D, then G, then the EMA of G:
  * D: non-saturating loss on DiffAugmented real and generated scans, plus
    the R1 penalty (gamma / 2) * E||grad D(aug(x_real))||^2 every
    ``r1_every`` steps, weighted by ``r1_every`` (lazy regularization; with
    ``r1_every = 1`` it is applied every step).
  * G: non-saturating loss through the updated D. The generator's forward
    pass from the D step is reused through its VJP (the authors reuse it
    the same way), so G runs forward once per step.
"""

from __future__ import annotations

import functools
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import optax
from jax import lax

from dusty_jax import augment, losses, models, projection
from dusty_jax.sensor import SensorSpec

AXIS = 'data'


class TrainState(flax.struct.PyTreeNode):
  step: jax.Array
  g_params: Any
  d_params: Any
  g_opt: Any
  d_opt: Any
  ema_params: Any


@flax.struct.dataclass
class Setup:
  """Static pieces of training derived from the config (not a pytree leaf)."""
  generator: Any = flax.struct.field(pytree_node=False)
  discriminator: Any = flax.struct.field(pytree_node=False)
  g_tx: Any = flax.struct.field(pytree_node=False)
  d_tx: Any = flax.struct.field(pytree_node=False)
  model: str = flax.struct.field(pytree_node=False)
  sensor: SensorSpec = flax.struct.field(pytree_node=False)
  latent_dim: int = flax.struct.field(pytree_node=False)
  tau: float = flax.struct.field(pytree_node=False)
  r1_gamma: float = flax.struct.field(pytree_node=False)
  r1_every: int = flax.struct.field(pytree_node=False)
  ema_decay: float = flax.struct.field(pytree_node=False)
  policy: tuple = flax.struct.field(pytree_node=False)


def make_setup(config, sensor: SensorSpec) -> Setup:
  g, d = models.build(config.model, sensor, config.latent_dim, config.ch_base,
                      config.ch_max, config.impl or None)
  tx = lambda: optax.adam(config.lr, b1=config.beta1, b2=config.beta2, eps=1e-8)
  # EMA half-life in images, as the authors' smoothing_kimg.
  ema_decay = 0.5 ** (config.batch_size / max(config.ema_halflife_kimg * 1000, 1e-8))
  policy = tuple(p for p in config.augment.split(',') if p)
  return Setup(g, d, tx(), tx(), config.model, sensor, config.latent_dim,
               config.tau, config.r1_gamma, max(int(config.r1_every), 1),
               float(ema_decay), policy)


def init_state(setup: Setup, key) -> TrainState:
  kg, kd = jax.random.split(key)
  z = jnp.zeros((1, setup.latent_dim))
  g_params = setup.generator.init(kg, z)
  d_params = setup.discriminator.init(kd, jnp.zeros((1,) + setup.sensor.shape))
  return TrainState(step=jnp.zeros((), jnp.int32), g_params=g_params,
                    d_params=d_params, g_opt=setup.g_tx.init(g_params),
                    d_opt=setup.d_tx.init(d_params),
                    ema_params=jax.tree.map(jnp.copy, g_params))


def generate(setup: Setup, params, z, key, train=True):
  raw = setup.generator.apply(params, z)
  return models.render(setup.model, raw, key, setup.tau, train)


def train_step(setup: Setup, state: TrainState, batch, key, axis_name=AXIS):
  """One D + G + EMA update on this device's share of the batch.

  ``batch``: (b, H, W) real scans in normalised inverse depth. Must run
  where ``axis_name`` is bound (see parallel.py), even on one device.
  """
  key = jax.random.fold_in(key, state.step)
  key = jax.random.fold_in(key, lax.axis_index(axis_name))
  kz, kmask, kar, kaf, kag = jax.random.split(key, 5)
  b = batch.shape[0]
  z = jax.random.normal(kz, (b, setup.latent_dim))
  d_apply = lambda p, x: setup.discriminator.apply(p, x)
  aug = lambda k, x: augment.diff_augment(k, x, setup.policy)

  # Generator forward once; its VJP serves the G update below.
  fake, g_vjp = jax.vjp(
      lambda p: generate(setup, p, z, kmask)['scan'], state.g_params)

  # --- Discriminator ---------------------------------------------------
  do_r1 = setup.r1_gamma > 0
  r1_now = (state.step % setup.r1_every) == 0

  def d_objective(dp):
    real_aug = aug(kar, batch)
    real_logits = d_apply(dp, real_aug)
    fake_logits = d_apply(dp, aug(kaf, lax.stop_gradient(fake)))
    adv = losses.d_loss(real_logits, fake_logits)
    r1 = jnp.zeros(())
    if do_r1:
      penalty = lambda: losses.r1_penalty(lambda x: d_apply(dp, x), real_aug)
      r1 = penalty() if setup.r1_every == 1 else lax.cond(
          r1_now, penalty, lambda: jnp.zeros(()))
    total = adv + 0.5 * setup.r1_gamma * setup.r1_every * r1
    return total, {'loss_d': adv, 'r1': r1,
                   'd_real': real_logits.mean(), 'd_fake': fake_logits.mean()}

  d_grads, d_metrics = jax.grad(d_objective, has_aux=True)(state.d_params)
  d_grads = lax.pmean(d_grads, axis_name)
  d_updates, d_opt = setup.d_tx.update(d_grads, state.d_opt, state.d_params)
  d_params = optax.apply_updates(state.d_params, d_updates)

  # --- Generator, through the updated D --------------------------------
  def g_objective(scan):
    return losses.g_loss(d_apply(d_params, aug(kag, scan)))

  loss_g, dscan = jax.value_and_grad(g_objective)(fake)
  (g_grads,) = g_vjp(dscan)
  g_grads = lax.pmean(g_grads, axis_name)
  g_updates, g_opt = setup.g_tx.update(g_grads, state.g_opt, state.g_params)
  g_params = optax.apply_updates(state.g_params, g_updates)

  ema = jax.tree.map(lambda e, p: setup.ema_decay * e + (1 - setup.ema_decay) * p,
                     state.ema_params, g_params)
  # 'r1' is 0 on steps that skip the penalty.
  metrics = dict(d_metrics, loss_g=loss_g,
                 drop_rate=jnp.mean(fake <= projection.ALPHA))
  metrics = lax.pmean(metrics, axis_name)
  new_state = state.replace(step=state.step + 1, g_params=g_params,
                            d_params=d_params, g_opt=g_opt, d_opt=d_opt,
                            ema_params=ema)
  return new_state, metrics


def step_fn(setup: Setup):
  return functools.partial(train_step, setup)
