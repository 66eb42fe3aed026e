"""Training the encoder (encoder.py) of one frozen generator.

On the generator's own samples (z, G(z)): the input is G(z) with the drops G
samples and a random corruption (none, drop, beams or noise, as the invert
CLI's ``--corrupt``), and the loss is

    w_latent * |E(x) - z|^2 / d  +  w_rec * mean |x_tilde(E(x)) - x_tilde(z)|
      + w_real * (the inversion's masked L1 of x_tilde(E(x_r)) to real scans x_r)

The reconstruction term, through the frozen G, is what the inversion itself
measures, and it lets E ignore latent directions G does not use; its target
is G's *complete* inverse depth, so E learns to complete what was dropped.
The latent term pins E to the z that made the scan where G is flat in z, and
gives a useful gradient from the first step, when x_tilde(E(x)) is still far
from anything; its weight is small, since it starts far above the
reconstruction term and, for a small generator, pulls along latent
directions that do not change the scan. The last term, on the run's own
training scans (corrupted the same way, fitted to the clean scan's
returns), is the inversion's objective itself: it closes the gap between
G's samples and real scans. :func:`train` is resumable;
``python -m dusty_jax.tools.train_encoder`` runs it on a run directory and
writes ``encoder.npz`` beside it (generator.py).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
import tqdm

from dusty_jax import checkpoint, corrupt, errors, parallel
from dusty_jax.codec import ALPHA
from dusty_jax.encoder import EncoderSettings, init_variables, module, project

DIRECTORY = 'encoder'  # its training's checkpoints, in the run directory
OPTIONS_FILE = 'options.json'  # in DIRECTORY: the options a resumed training keeps
SAVE_EVERY = 250  # steps between checkpoints


@dataclasses.dataclass(frozen=True)
class TrainOptions:
  """How an encoder is trained (tools/train_encoder.py's flags)."""
  steps: int = 600
  batch: int = 32
  lr: float = 3e-3
  w_latent: float = 0.1
  w_rec: float = 1.0
  # The inversion's own objective on the run's training scans (corrupted as
  # above, fitted to the clean scan's returns): closes the gap between G's
  # samples and real scans. 0: G's samples only.
  w_real: float = 1.0
  real_batch: int = 16
  # Random corruption of each input, each with probability 1/4: none,
  # drop:U(0.5, max_drop), beams:K for K in BEAMS, noise:U(0, max_noise).
  max_drop: float = 0.95
  max_noise: float = 0.02
  seed: int = 0


BEAMS = (2, 4, 8)


def corrupt_one(key, scan, sensor, opts: TrainOptions):
  """One of: the scan as is, random drops, every K-th ring, range noise."""
  kc, kd, kf, kb, kn, ks = jax.random.split(key, 6)
  fraction = jax.random.uniform(kf, (), minval=0.5, maxval=opts.max_drop)
  k = jnp.asarray(BEAMS)[jax.random.randint(kb, (), 0, len(BEAMS))]
  rows = (jnp.arange(scan.shape[0]) % k) == 0
  sigma = jax.random.uniform(ks, (), maxval=opts.max_noise)
  options = jnp.stack([
      scan,
      corrupt.drop(kd, scan, fraction),
      jnp.where(rows[:, None], scan, ALPHA),
      corrupt.noise(kn, scan, sigma, sensor)])
  return options[jax.random.randint(kc, (), 0, 4)]


def samples(params, key, batch: int, opts: TrainOptions, impl: str | None = None):
  """(z, inputs, complete x_tilde) of ``batch`` samples of the generator."""
  kz, km, kc = jax.random.split(key, 3)
  z = project(jax.random.normal(kz, (batch, params.latent_dim)))
  raw = params.module(impl).apply(params.variables, z)
  out = params.variant.compose(raw, km, params.tau, train=False)  # as sample() gives
  keys = jax.random.split(kc, batch)
  inputs = jax.vmap(lambda k, s: corrupt_one(k, s, params.sensor, opts))(keys, out['scan'])
  return z, inputs, out['inv_depth']


def masked_l1(x_tilde, target):
  """Per scan: the mean |x_tilde - target| over the target's returns (the
  inversion's objective, inversion.objective)."""
  valid = jnp.isfinite(target) & (target > ALPHA)
  diff = jnp.where(valid, jnp.abs(x_tilde - jnp.where(valid, target, 0.0)), 0.0)
  return diff.sum(axis=(-2, -1)) / jnp.maximum(valid.sum(axis=(-2, -1)), 1)


def loss_fn(enc_vars, params, z, inputs, target, opts: TrainOptions,
            impl: str | None = None, real_inputs=None, real=None):
  """(total, (latent term, reconstruction term, real-scan term)) of a batch."""
  enc, gen = module(params, impl), params.module(impl)
  decode = lambda e: params.variant.decode_inv_depth(gen.apply(params.variables, e))
  e = project(enc.apply(enc_vars, inputs))
  latent = jnp.mean(jnp.sum((e - z) ** 2, axis=-1)) / params.latent_dim
  rec = jnp.mean(jnp.abs(decode(e) - target))
  fit = jnp.zeros(())
  if real is not None:
    fit = jnp.mean(masked_l1(decode(project(enc.apply(enc_vars, real_inputs))), real))
  total = opts.w_latent * latent + opts.w_rec * rec + opts.w_real * fit
  return total, (latent, rec, fit)


def optimizer(opts: TrainOptions):
  return optax.adam(optax.cosine_decay_schedule(opts.lr, opts.steps, alpha=0.05))


@functools.partial(jax.jit, static_argnames=('opts', 'impl'))
def train_step(params, enc_vars, opt_state, key, opts: TrainOptions,
               impl: str | None = None, real=None):
  """One Adam step of the encoder on fresh samples (and ``real`` training
  scans (B, H, W), normalised inverse depth, if given); G stays frozen."""
  k_gen, k_real = jax.random.split(key)
  z, inputs, target = samples(params, k_gen, opts.batch, opts, impl)
  real_inputs = None
  if real is not None:
    keys = jax.random.split(k_real, len(real))
    real_inputs = jax.vmap(lambda k, s: corrupt_one(k, s, params.sensor, opts))(keys, real)
  (loss, (latent, rec, fit)), grads = jax.value_and_grad(loss_fn, has_aux=True)(
      enc_vars, params, z, inputs, target, opts, impl, real_inputs, real)
  updates, opt_state = optimizer(opts).update(grads, opt_state, enc_vars)
  enc_vars = optax.apply_updates(enc_vars, updates)
  return enc_vars, opt_state, {'loss': loss, 'latent': latent, 'rec': rec, 'real': fit}


def check_options(directory: str, opts: TrainOptions) -> None:
  """A resumed training must keep its options (the schedule depends on
  them): records them in ``directory`` the first time, refuses others after."""
  path = os.path.join(directory, OPTIONS_FILE)
  mine = dataclasses.asdict(opts)
  if os.path.isfile(path):
    with open(path) as fh:
      saved = json.load(fh)
    if saved != mine:
      diff = {k: (saved.get(k), v) for k, v in mine.items() if saved.get(k) != v}
      raise ValueError(f'{directory} holds an encoder training with other options '
                       f'(saved, given): {diff}; give the same flags to resume, or '
                       'remove that folder to start again')
  else:
    os.makedirs(directory, exist_ok=True)
    with open(path, 'w') as fh:
      json.dump(mine, fh, indent=2)


def train(params, directory: str, opts: TrainOptions = TrainOptions(), real=None,
          settings: EncoderSettings = EncoderSettings(), progress: bool = True):
  """Trains an encoder for the frozen generator ``params``.

  ``real``: the run's training scans (N, H, W), normalised inverse depth, for
  the real-scan term (None: G's samples only; needs ``opts.w_real == 0``).
  Checkpoints into ``directory`` every SAVE_EVERY steps and at the end; a
  call on the same directory resumes there (with the same options). Holds
  ``directory`` alone while it runs (parallel.hold_workdir): a second
  training there is refused, naming the first. Returns (variables, info):
  info holds the steps, the options and the last step's loss terms.
  """
  if real is None and opts.w_real > 0:
    raise ValueError(f'w_real={opts.w_real}: the real-scan term needs the training '
                     'scans (real=), or give w_real=0')
  with parallel.hold_workdir(directory):
    return _train(params, directory, opts, real, settings, progress)


def _train(params, directory, opts, real, settings, progress):
  params = params.replace(encoder=None, encoder_settings=None)
  check_options(directory, opts)
  k_init, key = jax.random.split(jax.random.key(opts.seed))
  enc_vars = init_variables(k_init, params, settings)
  state = {'encoder': enc_vars, 'opt': optimizer(opts).init(enc_vars)}
  mngr = checkpoint.manager(directory, keep=2, cleanup_tmp=True)  # held alone
  state, step = checkpoint.restore_latest(mngr, state)
  start = 0 if step is None else step
  params = params.replace(encoder_settings=settings)
  bar = tqdm.tqdm(total=opts.steps, initial=start, desc='encoder', unit='step',
                  file=sys.stderr, disable=not progress)
  # Committed to the device as train_step's outputs are, so that the second
  # step does not compile again.
  enc_vars, opt_state = jax.device_put((state['encoder'], state['opt']),
                                       jax.local_devices()[0])
  t0, metrics = time.time(), {}
  for i in range(start, opts.steps):
    batch = None
    if real is not None and opts.w_real > 0:
      pick = np.random.default_rng((opts.seed, i)).integers(0, len(real), opts.real_batch)
      batch = real[pick]
    enc_vars, opt_state, metrics = train_step(
        params, enc_vars, opt_state, jax.random.fold_in(key, i), opts, real=batch)
    if (i + 1) % 50 == 0 or i + 1 == opts.steps:
      bar.set_postfix({k: f'{float(v):.4f}' for k, v in metrics.items()})
    if (i + 1) % SAVE_EVERY == 0 or i + 1 == opts.steps:
      with errors.interrupts_deferred():  # orbax's save is not cut half-way
        checkpoint.save(mngr, i + 1, {'encoder': enc_vars, 'opt': opt_state}, force=True)
    bar.update(1)
  bar.close()
  checkpoint.wait(mngr)
  info = {'steps': opts.steps, 'options': dataclasses.asdict(opts),
          'final': {k: float(v) for k, v in metrics.items()},
          'seconds_this_call': round(time.time() - t0, 1)}
  return jax.device_get(enc_vars), info
