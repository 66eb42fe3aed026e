"""GAN training: the train state, pure step functions, and the loop.

One step is ``train_step(state, batch, key) -> (state, metrics)``, written
once per device with the named axis ``'data'`` (gradients and metrics are
``pmean``-ed over it) and wrapped for the devices at hand in parallel.py.

A step composes three pure functions, each tested alone: ``d_step``, then
``g_step``, then ``ema_update``:
  * D: non-saturating loss on DiffAugmented real and generated scans, plus
    the R1 penalty (gamma / 2) * E||grad D(aug(x_real))||^2. By default on
    every step, as the authors' trainer does. With ``r1_every = k > 1`` it is
    lazy (StyleGAN2): applied every k steps, weighted by k, folded into that
    step's D update, with StyleGAN2's Adam adjustment for D (lr x c, betas
    ^ c, c = k / (k + 1)).
  * G: non-saturating loss through the updated D, plus the point-drop terms
    beyond the paper (drops.py; all off by default). The generator's forward
    pass from the D step is reused through its VJP (the authors reuse it
    the same way), so G runs forward once per step.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import sys
import time
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax
import tqdm
from jax import lax

from dusty_jax import (after_training, augment, checkpoint, codec, configs, drops, errors,
                       generator, losses, models, parallel, runs, sampling, writers)
from dusty_jax import sensor as sensor_lib
from dusty_jax.data import arrays, pipeline
from dusty_jax.parallel import AXIS
from dusty_jax.sensor import SensorSpec


class TrainState(flax.struct.PyTreeNode):
  step: jax.Array
  g_params: Any
  d_params: Any
  g_opt: Any
  d_opt: Any
  ema_params: Any


static = lambda: flax.struct.field(pytree_node=False)


@flax.struct.dataclass
class Setup:
  """Static pieces of training derived from the config (no pytree leaves)."""
  settings: models.ModelSettings = static()
  sensor: SensorSpec = static()
  generator: Any = static()
  discriminator: Any = static()
  g_tx: Any = static()
  d_tx: Any = static()
  r1_gamma: float = static()
  r1_every: int = static()
  ema_decay: float = static()
  ema_halflife_img: float = static()
  ema_rampup: float = static()
  batch_size: int = static()
  policy: tuple = static()
  augment_style: str = static()
  drops: drops.DropOptions = static()


def make_setup(config, sensor: SensorSpec) -> Setup:
  settings = configs.model_settings(config)
  impl = config.impl or None
  r1_every = config.r1_every
  def tx(lazy_every=1):
    # StyleGAN2's lazy regularisation: D's Adam sees k / (k + 1) of the
    # schedule (mb_ratio), so its lr and betas are adjusted.
    c = lazy_every / (lazy_every + 1) if lazy_every > 1 else 1.0
    return optax.adam(config.lr * c, b1=config.beta1 ** c, b2=config.beta2 ** c,
                      eps=config.adam_eps)
  policy = tuple(p for p in config.augment.split(',') if p)
  style = config.augment_style
  augment.check(policy, style)
  return Setup(
      settings=settings, sensor=sensor,
      generator=settings.generator(sensor, impl),
      discriminator=settings.discriminator(sensor, impl),
      g_tx=tx(), d_tx=tx(r1_every if config.r1_gamma > 0 else 1),
      r1_gamma=float(config.r1_gamma), r1_every=r1_every,
      # EMA half-life in images, as the authors' smoothing_kimg.
      ema_decay=float(0.5 ** (config.batch_size /
                              max(config.ema_halflife_kimg * 1000, 1e-8))),
      ema_halflife_img=config.ema_halflife_kimg * 1000.0,
      ema_rampup=float(config.ema_rampup),
      batch_size=config.batch_size, policy=policy, augment_style=style,
      drops=drops.DropOptions.from_config(config.drops))


def init_state(setup: Setup, key, ring_keep=None) -> TrainState:
  """Fresh networks and optimisers. ``ring_keep``: (H,) the training data's
  keep rate per ring, where the model has a ring bias
  (ModelSettings.ring_bias): the measurability starts at it (without it, the
  ring offsets start at 0)."""
  kg, kd = jax.random.split(key)
  z = jnp.zeros((1, setup.settings.latent_dim))
  g_params = drops.init_biases(setup.drops, jax.jit(setup.generator.init)(kg, z), ring_keep)
  d_params = jax.jit(setup.discriminator.init)(kd, jnp.zeros((1,) + setup.sensor.shape))
  return TrainState(step=jnp.zeros((), jnp.int32), g_params=g_params,
                    d_params=d_params, g_opt=setup.g_tx.init(g_params),
                    d_opt=setup.d_tx.init(d_params),
                    ema_params=jax.tree.map(jnp.copy, g_params))


@flax.struct.dataclass
class Fake:
  """Generated scans as G's loss sees them (``g_step``), each (B, H, W):
  ``scan``, what D sees; and, where drops terms differentiate them
  (drops.add_penalties), the straight-through keep-``mask``, the detached
  head's expected keep ``head_keep`` (drops.rate_head_only); None otherwise."""
  scan: jax.Array
  mask: jax.Array | None = None
  head_keep: jax.Array | None = None


def fake_scans(setup: Setup, params, z, keys, train=True, detached_head=False):
  """Generator forward and rendering; ``keys``: one per example. With
  ``detached_head`` the dict also holds ``head_keep``: the measurability of
  the head applied to the trunk's features under stop_gradient (the same
  values; its gradient reaches the head alone: drops.rate_head_only). With
  drops.mask_detached the composition's measurability is that one."""
  variant = setup.settings.variant
  detach = detached_head or setup.drops.mask_detached
  raw = setup.generator.apply(params, z, detached_head=detach)
  raw, raw_head = raw if detach else (raw, None)
  if setup.drops.mask_detached:  # depth from the trunk, the mask from the head alone
    raw = jnp.concatenate([raw[..., :1], raw_head[..., 1:]], axis=-1)
  out = variant.compose_per_example(raw, keys, setup.settings.tau, train)
  if detached_head:
    out['head_keep'] = variant.measurability(variant.logit(raw_head))
  return out


# ----------------------------------------------------------------------------
# The pure pieces of a step. With ``axis_name`` (inside parallel.py's
# wrapper) gradients and metrics are averaged over devices; with None they
# are this call's own, which is how the tests run them alone.
# ----------------------------------------------------------------------------


def _pmean(tree, axis_name):
  return tree if axis_name is None else lax.pmean(tree, axis_name)


def _local(tree, axis_name):
  # Differentiate with respect to per-device copies of replicated parameters:
  # the gradients are then this device's own, and pmean averages them.
  # (Differentiating the replicated values directly would make shard_map
  # psum the cotangents itself.)
  return tree if axis_name is None else lax.pcast(tree, (axis_name,), to='varying')


def _augment(setup: Setup, keys, x):
  """What D sees of scans ``x`` (B, H, W): DiffAugmented, one key per example."""
  return augment.per_example(keys, x, setup.policy, setup.augment_style)


def d_step(setup: Setup, d_params, d_opt, real, fake, keys, r1_now=True,
           axis_name=None):
  """One discriminator update: (d_params, d_opt, metrics).

  Non-saturating loss on DiffAugmented ``real`` and ``fake`` (B, H, W) scans
  (``keys``: (real, fake) augmentation keys, one per example each), plus
  (gamma / 2) * k * R1 on the augmented reals when ``r1_now`` (k =
  r1_every; R1 is 0 on steps that skip it).
  """
  k_real, k_fake = keys
  d_apply = setup.discriminator.apply

  def objective(dp):
    real_aug = _augment(setup, k_real, real)
    real_logits = d_apply(dp, real_aug)
    fake_logits = d_apply(dp, _augment(setup, k_fake, lax.stop_gradient(fake)))
    adv = losses.d_loss(real_logits, fake_logits)
    r1 = jnp.zeros(())
    if setup.r1_gamma > 0:
      penalty = lambda: losses.r1_penalty(lambda x: d_apply(dp, x), real_aug)
      skip = lambda: _local(jnp.zeros(()), axis_name)
      r1 = penalty() if setup.r1_every == 1 else lax.cond(r1_now, penalty, skip)
    total = adv + 0.5 * setup.r1_gamma * setup.r1_every * r1
    return total, {'loss_d': adv, 'r1': r1,
                   'd_real': real_logits.mean(), 'd_fake': fake_logits.mean()}

  grads, metrics = jax.grad(objective, has_aux=True)(_local(d_params, axis_name))
  grads = _pmean(grads, axis_name)
  updates, d_opt = setup.d_tx.update(grads, d_opt, d_params)
  return optax.apply_updates(d_params, updates), d_opt, metrics


def g_step(setup: Setup, g_params, g_opt, d_params, fake: Fake, fake_vjp, key,
           axis_name=None, real=None):
  """One generator update through ``d_params``: (g_params, g_opt, loss_g).

  ``fake``: the generated scans (a :class:`Fake`) and ``fake_vjp`` the VJP
  of the generator's forward pass that made them (``jax.vjp``), so the
  forward pass of the D step serves here too (the authors reuse it the
  same way). ``key``: the augmentation keys, one per example. ``real``: the
  real batch's (scans, keep-masks), which the drops terms compare with
  (drops.add_penalties). ``loss_g`` is the adversarial loss alone.
  """
  d_local = _local(d_params, axis_name)

  def objective(fake):
    adv = losses.g_loss(setup.discriminator.apply(d_local, _augment(setup, key, fake.scan)))
    return drops.add_penalties(setup.drops, setup.sensor, adv, fake, real, axis_name), adv

  (_, loss_g), dfake = jax.value_and_grad(objective, has_aux=True)(fake)
  (grads,) = fake_vjp(dfake)
  grads = _pmean(grads, axis_name)
  updates, g_opt = setup.g_tx.update(grads, g_opt, g_params)
  return optax.apply_updates(g_params, updates), g_opt, loss_g


def ema_decay(setup: Setup, step):
  """The EMA decay at ``step`` (0-based): 0.5 ** (batch / half-life images).

  With ``ema_rampup`` the half-life grows with the images seen, up to
  ema_halflife_kimg (StyleGAN2), so early samples are not dominated by the
  initialisation.
  """
  if not setup.ema_rampup:
    return setup.ema_decay
  seen = (step + 1).astype(jnp.float32) * setup.batch_size
  halflife = jnp.minimum(setup.ema_halflife_img, seen * setup.ema_rampup)
  return 0.5 ** (setup.batch_size / jnp.maximum(halflife, 1e-8))


def ema_update(ema_params, params, decay):
  """decay * ema + (1 - decay) * params, leaf by leaf."""
  return jax.tree.map(lambda e, p: decay * e + (1 - decay) * p, ema_params, params)


def train_step(setup: Setup, state: TrainState, batch, key, axis_name=AXIS):
  """One D + G + EMA update on this device's share of the batch.

  ``batch``: (b, H, W) real scans in normalised inverse depth. Must run
  where ``axis_name`` is bound (see parallel.py), even on one device.
  """
  # Randomness per example, from (key, step, global example index): the same
  # whatever the number of devices, so 1- and N-device runs agree.
  b = batch.shape[0]
  # Drops in the discriminator's input are ALPHA, as generated ones.
  batch = jnp.where(batch <= codec.ALPHA, codec.ALPHA, batch)
  key = jax.random.fold_in(key, state.step)
  ids = lax.axis_index(axis_name) * b + jnp.arange(b)
  keys = jax.vmap(lambda i: jax.random.split(jax.random.fold_in(key, i), 5))(ids)
  kz, kmask, kar, kaf, kag = (keys[:, j] for j in range(5))
  z = jax.vmap(lambda k: jax.random.normal(k, (setup.settings.latent_dim,)))(kz)

  # Generator forward once; its VJP serves the G update. The keep-mask is
  # an output G is differentiated through where a drops term needs it, else
  # aux (for the metrics).
  needs_mask = setup.drops.g_needs_mask
  def fakes(p):
    out = fake_scans(setup, p, z, kmask, detached_head=setup.drops.rate_head_only)
    if not needs_mask:
      return Fake(scan=out['scan']), out['mask']
    return Fake(scan=out['scan'], mask=out['mask'], head_keep=out.get('head_keep'))
  real = (batch, (batch > codec.ALPHA).astype(batch.dtype))
  if needs_mask:
    fake, fake_vjp = jax.vjp(fakes, _local(state.g_params, axis_name))
    mask = fake.mask
  else:
    fake, fake_vjp, mask = jax.vjp(fakes, _local(state.g_params, axis_name), has_aux=True)

  d_params, d_opt, d_metrics = d_step(
      setup, state.d_params, state.d_opt, batch, fake.scan, (kar, kaf),
      (state.step % setup.r1_every) == 0, axis_name)
  g_params, g_opt, loss_g = g_step(setup, state.g_params, state.g_opt, d_params,
                                   fake, fake_vjp, kag, axis_name, real)
  ema = ema_update(state.ema_params, g_params, ema_decay(setup, state.step))
  metrics = dict(d_metrics, loss_g=loss_g,
                 **drops.diagnostics(fake.scan, mask, batch, axis_name))
  metrics = lax.pmean(metrics, axis_name)
  new_state = state.replace(step=state.step + 1, g_params=g_params,
                            d_params=d_params, g_opt=g_opt, d_opt=d_opt,
                            ema_params=ema)
  return new_state, metrics


def step_fn(setup: Setup):
  return functools.partial(train_step, setup)


# ----------------------------------------------------------------------------
# The loop.
# ----------------------------------------------------------------------------


class NonFiniteLossError(errors.UserError, FloatingPointError):
  """Training diverged (a NaN or inf metric); says what a rerun resumes from."""


def generator_params(setup: Setup, variables, angles, tolerance=0.0):
  """A GeneratorParams of these variables (e.g. the EMA) for sampling."""
  return generator.GeneratorParams(variables=variables, angles=jnp.asarray(angles),
                                   sensor=setup.sensor, settings=setup.settings,
                                   tolerance=tolerance)


def init_run(workdir: str, config, params) -> None:
  """Starts a run directory from given generator weights (e.g. the authors'):
  config, generator description and a step-0 checkpoint whose G and EMA
  hold ``params.variables`` and whose D and optimisers are fresh. Drop
  levels fitted after training (levels.py) go to the run's levels file, at
  step 0, not into the trained weights."""
  setup = make_setup(config, params.sensor)
  variables = runs.record_given(workdir, config, params, setup.settings)
  state = init_state(setup, jax.random.key(config.seed)).replace(g_params=variables,
                                                                 ema_params=variables)
  mngr = checkpoint.manager(workdir, keep=config.keep_checkpoints)
  with errors.interrupts_deferred():  # orbax's save is not cut half-way
    checkpoint.save(mngr, 0, state, force=True)
    checkpoint.wait(mngr)


@jax.jit
def _all_finite(tree):
  return jnp.all(jnp.stack([jnp.isfinite(v).all() for v in jax.tree.leaves(tree)]))


def _check_finite(records, last_checkpoint, ema_params=None):
  """``last_checkpoint``: the newest saved step (None: none yet), all of
  whose metrics were finite. ``ema_params``: the EMA generator after the
  last record's step, checked too (no training metric reads it)."""
  if ema_params is not None and records and not bool(_all_finite(ema_params)):
    records = records[:-1] + [(records[-1][0], {**records[-1][1], 'ema_params': np.nan})]
  for s, m in records:
    bad = {k: v for k, v in m.items() if not np.isfinite(v)}
    if bad:
      kept = ('no checkpoint was saved yet, so a rerun starts afresh'
              if last_checkpoint is None else
              f'the last checkpoint, step {last_checkpoint}, is kept and a rerun '
              'resumes from it')
      raise NonFiniteLossError(
          f'non-finite training metrics at step {s}: {bad}; training stopped; '
          f'{kept} (lower lr, or raise r1_gamma)')


def _save_images(path, params, z, key):
  out = jax.device_get(sampling.generate(params, z, key))
  fig = writers.scan_figure(
      [writers.Column('sample scan', writers.DEPTH, out['scan']),
       writers.Column('complete depth x_tilde', writers.DEPTH, out['inv_depth']),
       writers.Column('measurability', writers.PROBABILITY, out['measurability'],
                      'probability of a return')],
      params.sensor, row_label='sample')
  writers.save_figure(fig, path)


def _time_to_save(config, saved_at: float, log_now: bool) -> bool:
  """Whether checkpoint_minutes have passed since the last checkpoint. Every
  process of a run must agree (a save is collective): with several, process
  0's clock decides, at log steps."""
  if not config.checkpoint_minutes:
    return False
  due = time.monotonic() - saved_at >= 60 * config.checkpoint_minutes
  if jax.process_count() == 1:
    return due
  return log_now and parallel.all_texts('save', 'yes' if due else '')[0] == 'yes'


def train_and_evaluate(config, workdir: str, log=print,
                       peer_timeout: float = parallel.PEER_TIMEOUT_S) -> TrainState:
  """Trains from scratch or resumes from the latest checkpoint in ``workdir``,
  then runs the steps ``config.after_training`` names (after_training.py), in
  order.

  Holds ``workdir`` alone while it runs (parallel.hold_workdir): a second
  training on it is refused. In a run of several processes, a process whose
  peer is lost ends within about ``peer_timeout`` seconds, saying which
  checkpoint a rerun of all processes resumes from (parallel.PeerWatch).
  """
  sensor = configs.validate(config)  # the one place the config's sensor is read
  augment.check_config(config)
  watch = parallel.PeerWatch(peer_timeout, functools.partial(runs.peer_lost, workdir))
  try:
    with parallel.hold_workdir(workdir):
      state, run = _train(config, sensor, workdir, log)
      for name in configs.after_training(config):
        run = after_training.STEPS[name](run)
  except BaseException as e:
    watch.close()
    if (any(parallel.is_peer_loss(x) for x in errors.causes(e))
        and not errors.show_traceback()):
      watch.lost(_first_line(e))
    raise
  watch.finish()
  return state


def _first_line(e: BaseException) -> str:
  text = str(e).strip()
  return text.splitlines()[0][:200] if text else type(e).__name__


class _Progress:
  """The loop's metrics: kept on the device until a log step, then fetched
  (:meth:`fetch`), averaged into the run's metrics (writers.MetricWriter)
  and onto the progress bar (:meth:`write`)."""

  def __init__(self, config, workdir: str, start: int, enabled: bool):
    self.batch_size = config.batch_size
    self.pending = []  # (step, device metrics) not yet fetched.
    self.last = (time.time(), start)  # when the last log step was, and which
    self.writer = writers.MetricWriter(workdir, enabled=enabled, resume_step=start)
    self.bar = tqdm.tqdm(total=config.num_steps, initial=start, disable=not enabled,
                         unit='step', dynamic_ncols=True, file=sys.stderr)

  def fetch(self) -> list:
    """[(step, {name: float})] of the steps since the last fetch."""
    records = [(s, {k: float(v) for k, v in parallel.to_host(m).items()})
               for s, m in self.pending]
    self.pending = []
    return records

  def write(self, done: int, records: list):
    now = time.time()
    rate = (done - self.last[1]) * self.batch_size / max(now - self.last[0], 1e-9)
    self.last = (now, done)
    mean = {k: float(np.mean([m[k] for _, m in records])) for k in records[-1][1]}
    mean['images_per_sec'] = rate
    self.writer.write(done, mean)
    self.bar.set_postfix(img_s=f'{rate:.1f}', d=f'{mean["loss_d"]:.3f}',
                         g=f'{mean["loss_g"]:.3f}', drop=f'{mean["drop_rate"]:.2f}')


@dataclasses.dataclass(frozen=True)
class Start:
  """What a run starts from (:func:`_start`)."""
  data_dir: str  # the prepared dataset
  data: pipeline.TrainingData  # its training split
  angles: np.ndarray  # (2, H, W), the dataset's
  batches: pipeline.Batches
  mngr: Any  # the run's checkpoint manager
  state: TrainState  # placed on the mesh
  step: int  # the first step to train


def _start(config, workdir: str, setup: Setup, mesh, key, log) -> Start:
  """The training data, the run's files, and the state to start from: the
  latest checkpoint in ``workdir`` or, with none, fresh networks (``key``)."""
  sensor, is_main = setup.sensor, jax.process_index() == 0
  data_dir = pipeline.dataset_dir(config, sensor, log=log)
  # The data checked whole before the run writes anything of its own.
  arrays.check_sensor(data_dir, sensor, sensor_lib.source_of(config.sensor))
  data = pipeline.TrainingData(data_dir, sensor, config.data.memory_mb,
                               log=log if is_main else lambda m: None)
  angles = arrays.load_angles(data_dir, sensor)
  data.start_run(workdir, bool(checkpoint.saved_steps(workdir)), config.data.allow_changed,
                 write=is_main)
  batches = pipeline.Batches(data.depth, sensor, config.batch_size, config.seed,
                             jax.process_index(), jax.process_count())
  if is_main:
    runs.record(workdir, config, sensor, setup.settings, angles)
  mngr = checkpoint.manager(workdir, keep=config.keep_checkpoints,
                            keep_every=config.keep_every, cleanup_tmp=True,
                            log=log if is_main else None)
  state = init_state(setup, key, drops.ring_keep_rate(data.depth, sensor)
                     if setup.settings.ring_bias else None)
  # Placed on the mesh before restoring: each process then reads its own
  # part of the checkpoint, whatever process count wrote it.
  state, restored = checkpoint.restore_latest(mngr, parallel.replicate(state, mesh),
                                              log=log, set_aside=True)
  if restored is not None:
    log(f'resumed from step {restored} in {workdir}')
  return Start(data_dir, data, angles, batches, mngr, state,
               0 if restored is None else int(restored))


def _train(config, sensor: SensorSpec, workdir: str, log):
  """The loop: steps, logging and checkpoints. Returns (the final state, the
  run as the steps after training see it)."""
  runs.check_resumable(workdir, config, sensor)
  mesh = parallel.data_mesh()
  parallel.local_batch_size(config.batch_size, mesh)  # checks divisibility
  is_main = jax.process_index() == 0
  setup = make_setup(config, sensor)
  k_init, k_step, k_img = jax.random.split(jax.random.key(config.seed), 3)
  s = _start(config, workdir, setup, mesh, k_init, log)
  data, mngr, state, start = s.data, s.mngr, s.state, s.step
  step = parallel.data_parallel(step_fn(setup), mesh)
  progress = _Progress(config, workdir, start, is_main)
  if data.switched:  # allowed by data.allow_changed; data.json says from what
    log(f'training on from step {start} on changed data ({data.switched})')
    progress.writer.write(start, {'data_switched': 1.0})
  z_img = jax.random.normal(k_img, (config.num_images, setup.settings.latent_dim))
  done = start
  finished = False  # No error on its way: closing the writer may raise.
  saved_at = time.monotonic()  # of the last checkpoint, for checkpoint_minutes
  try:
    for i in range(start, config.num_steps):
      state, metrics = step(state, parallel.shard_batch(s.batches(i), mesh), k_step)
      done = i + 1
      progress.pending.append((done, metrics))
      # The first step's losses too: a newcomer sees numbers at once.
      log_now = (done == start + 1 or done % config.log_every == 0
                 or done == config.num_steps)
      ckpt_now = (done % config.checkpoint_every == 0 or done == config.num_steps
                  or _time_to_save(config, saved_at, log_now))
      if log_now or ckpt_now:
        records = progress.fetch()
        _check_finite(records, mngr.latest_step(), state.ema_params)
        data.check(done, mngr.latest_step(), functools.partial(parallel.all_texts, 'data'))
        progress.write(done, records)
      if ckpt_now:
        with errors.interrupts_deferred():  # orbax's save is not cut half-way
          checkpoint.save(mngr, done, state)
        saved_at = time.monotonic()
      if is_main and (done % config.image_every == 0 or done == config.num_steps):
        _save_images(os.path.join(workdir, 'images', f'step_{done:07d}.png'),
                     generator_params(setup, state.ema_params, s.angles), z_img,
                     jax.random.key(0))
      progress.bar.update()
    finished = True
  except KeyboardInterrupt:
    progress.bar.close()
    checkpoint.wait(mngr)
    raise runs.interrupted(done, mngr.latest_step()) from None
  finally:
    progress.bar.close()
    try:
      checkpoint.wait(mngr)
    except BaseException:
      finished = False
      raise
    finally:
      # A second failure (the disk that failed a checkpoint also fails the
      # metrics) must not replace the one already on its way.
      progress.writer.close(quiet=not finished)
  ema = generator_params(setup, parallel.to_host(state.ema_params), s.angles)
  return state, after_training.Trained(config=config, workdir=workdir, step=done, generator=ema,
                                       data_dir=s.data_dir, depth=data.depth, log=log)
