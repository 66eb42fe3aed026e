"""An encoder that starts GAN inversion: one forward pass, scan -> latent.

Beyond the paper (its inversion, like the authors' code, searches from a
random latent for 1000 Adam steps). ``Encoder`` maps a scan (normalised
inverse depth, drops at ALPHA, corrupted or not) to a latent on the
generator's sphere of radius sqrt(d); ``invert(params, scan,
init='encoder', num_steps=k)`` refines that with k steps of the search, and
``num_steps=0`` returns the encoder's answer alone.

It is trained per generator on the generator's own samples (z, G(z)): the
input is G(z) with the drops G samples and a random corruption (none, drop,
beams or noise, as the invert CLI's ``--corrupt``), and the loss is

    w_latent * |E(x) - z|^2 / d  +  w_rec * mean |x_tilde(E(x)) - x_tilde(z)|
      + w_real * (the inversion's masked L1 of x_tilde(E(x_r)) to real scans x_r)

The reconstruction term, through the frozen G, is what the inversion itself
measures, and it lets E ignore latent directions G does not use; its target
is G's *complete* inverse depth, so E learns to complete what was dropped.
The latent term pins E to the z that made the scan where G is flat in z, and
gives a useful gradient from the first step, when x_tilde(E(x)) is still
far from anything. The last term, on the run's own training scans
(corrupted the same way, fitted to the clean scan's returns), is the
inversion's objective itself: trained on G's samples alone, the encoder
started held-out scans hardly better than a random latent (masked L1 0.0997
vs 0.1020 on 8 simulated scans, the study's DUSty-I with the drops variant,
1000 steps), since at this scale G's samples are far from real scans
(1-NNA 99.6%). The latent term's weight is 0.1: the latent term starts at about 2
(|e - z|^2 / d = 2 (1 - cos)) against about 0.05 for the reconstruction, and
a small generator uses few of its latent directions, so at weight 1 it
dominates the gradient with directions that do not change the scan (with
weight 1 and lr 1e-3, 150 steps moved neither term: latent 1.98 -> 1.99,
reconstruction 0.059 -> 0.057 on the study's DUSty-I). ``python -m dusty_jax.tools.train_encoder`` trains one on
a run directory (resumable) and writes ``encoder.npz`` beside it.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import sys
import time
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import tqdm
from flax import traverse_util

from dusty_jax import checkpoint, codec, corrupt, errors, layers, parallel, xla_cache
from dusty_jax.codec import ALPHA
from dusty_jax.models import EqualConv, check_shape

FILE = 'encoder.npz'  # in a run directory, beside generator.json
DIRECTORY = 'encoder'  # its training's checkpoints, in the run directory
OPTIONS_FILE = 'options.json'  # in DIRECTORY: the options a resumed training keeps
SAVE_EVERY = 250  # steps between checkpoints
TRAIN_COMMAND = 'python -m dusty_jax.tools.train_encoder --workdir RUN'


@functools.partial(jnp.vectorize, signature='(d)->(d)')
def project(z):
  """Onto the sphere of radius sqrt(d), the generator's latent space, along
  the last axis.

  z is first divided by its largest magnitude (the projection does not
  change), so a norm whose square would underflow or overflow float32 still
  gives a point on the sphere; it is divided twice by the square root, as
  XLA divides by multiplying with the reciprocal, which flushes to 0 beyond
  |z| = 8.5e37. z = 0, whose nearest point on the sphere could be any, goes
  to the all-ones point, whose norm is sqrt(d). Finite z only: callers
  check what a user gives (errors.check_finite).
  """
  big = jnp.max(jnp.abs(z))
  root = jnp.sqrt(jnp.where(big > 0, big, 1.0))
  z = jnp.where(big > 0, z / root / root, 1.0)
  return optax.projections.projection_l2_sphere(z, jnp.sqrt(z.shape[-1]))


@dataclasses.dataclass(frozen=True)
class EncoderSettings:
  """The encoder network's size (the latent size and the sensor are the
  generator's). The default is about 1.1 M weights (4.4 MB float32)."""
  ch_base: int = 16
  ch_max: int = 64
  hidden: int = 256

  def __post_init__(self):
    for f in ('ch_base', 'ch_max', 'hidden'):
      v = getattr(self, f)
      if not isinstance(v, int) or v < 1:
        raise ValueError(f'encoder {f}={v!r}: must be a whole number >= 1')


class Encoder(nn.Module):
  """Scans (B, H, W) -> unprojected latents (B, latent_dim).

  Two input channels: the inverse depth of returned pixels (0 elsewhere) and
  the return mask (+-1), so a drop is never confused with a far return. Four
  4x4 stride-2 convolutions on the cylinder (the discriminator's), then two
  dense layers; equalized learning rate throughout.
  """
  sensor: Any
  latent_dim: int
  settings: EncoderSettings = EncoderSettings()
  impl: str = 'matmul'

  @nn.compact
  def __call__(self, scan):
    check_shape(self.sensor)
    valid = jnp.isfinite(scan) & (scan > ALPHA)
    x = jnp.stack([jnp.where(valid, scan, 0.0), 2.0 * valid - 1.0], axis=-1)
    for i in range(4):
      c = min(self.settings.ch_base << i, self.settings.ch_max)
      x = EqualConv(c, up=False, impl=self.impl, name=f'down{i}')(x)
      x = layers.leaky_act(x, self.param(f'down{i}_bias', nn.initializers.zeros, (c,)))
    x = x.reshape(x.shape[0], -1)
    for name, width in (('hidden', self.settings.hidden), ('out', self.latent_dim)):
      w = self.param(name, lambda k, s: jax.random.normal(k, s), (x.shape[-1], width))
      b = self.param(f'{name}_bias', nn.initializers.zeros, (width,))
      x = (x @ w) * (1.0 / math.sqrt(x.shape[-1]))
      x = layers.leaky_act(x, b) if name == 'hidden' else x + b
    return x


def module(params, impl: str | None = None) -> Encoder:
  """The encoder network of a generator's ``params`` (GeneratorParams)."""
  return Encoder(params.sensor, params.latent_dim, params.encoder_settings or
                 EncoderSettings(), impl or layers.default_impl())


def check_has_encoder(params, source: str = 'this generator', carry=()):
  """Refuses a generator without an encoder, saying what is possible:
  init='random', training one for a run, or the pretrained models ``carry``
  (names) that ship with one."""
  if params.encoder is None:
    shipped = (f"; the pretrained {', '.join(carry)} carr{'ies' if len(carry) == 1 else 'y'}"
               ' one (dusty_jax.load_pretrained(NAME))' if carry else '')
    raise ValueError(f"{source} has no encoder (init='encoder' needs one): use "
                     "init='random' (the authors' start), or train one for a training "
                     f'run with `{TRAIN_COMMAND}`{shipped}')


def encode(params, scans, impl: str | None = None):
  """Latents on the sphere (B, d) of scans (B, H, W): the encoder's answer.
  As in inversion, NaN and inf pixels count as drops (ALPHA); float16 and
  bfloat16 scans are refused (codec.check_precision); half-precision
  encoder weights compute in float32."""
  check_has_encoder(params)
  params = params.replace(encoder=errors.widen_half(params.encoder))
  scans = jnp.asarray(codec.check_precision(scans, 'scans'), jnp.float32)
  if errors.is_concrete(scans):  # traced: the caller cleaned them (inversion)
    scans = jnp.where(jnp.isfinite(scans), scans, ALPHA)
  xla_cache.enable()
  return _encode(params, scans, impl)


@functools.partial(jax.jit, static_argnames=('impl',))
def _encode(params, scans, impl):
  return project(module(params, impl).apply(params.encoder, scans))


def init_variables(key, params, settings: EncoderSettings = EncoderSettings()):
  """Fresh encoder variables for the generator ``params``."""
  enc = Encoder(params.sensor, params.latent_dim, settings, layers.default_impl())
  return jax.jit(enc.init)(key, jnp.zeros((1,) + params.sensor.shape))


# ----------------------------------------------------------------------------
# Training on the generator's own samples.
# ----------------------------------------------------------------------------


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
      checkpoint.save(mngr, i + 1, {'encoder': enc_vars, 'opt': opt_state}, force=True)
    bar.update(1)
  bar.close()
  checkpoint.wait(mngr)
  info = {'steps': opts.steps, 'options': dataclasses.asdict(opts),
          'final': {k: float(v) for k, v in metrics.items()},
          'seconds_this_call': round(time.time() - t0, 1)}
  return jax.device_get(enc_vars), info


# ----------------------------------------------------------------------------
# On disk: encoder.npz in a run directory; the same arrays inside an exported
# generator .npz under encoder/ (generator.py).
# ----------------------------------------------------------------------------


def flatten(variables) -> dict:
  return {k: np.asarray(v, np.float32)
          for k, v in traverse_util.flatten_dict(variables, sep='/').items()}


def unflatten(flat: dict):
  return traverse_util.unflatten_dict({k: jnp.asarray(v) for k, v in flat.items()},
                                      sep='/')


def save(path: str, variables, settings: EncoderSettings, info: dict | None = None):
  """Writes the encoder's variables and settings as one .npz (atomically)."""
  meta = {**(info or {}), 'settings': dataclasses.asdict(settings)}
  tmp = path + '.tmp.npz'
  np.savez_compressed(tmp, meta=np.asarray(json.dumps(meta)),
                      **{f'encoder/{k}': v for k, v in flatten(variables).items()})
  os.replace(tmp, path)
  return path


def load(path: str):
  """(variables, settings, meta) of an encoder written by :func:`save`."""
  try:
    with np.load(path, allow_pickle=False) as f:
      meta = json.loads(str(f['meta']))
      flat = {k[len('encoder/'):]: f[k] for k in f.files if k.startswith('encoder/')}
  except (OSError, ValueError, KeyError) as e:
    raise ValueError(f'{path}: not an encoder file ({e})') from None
  try:
    settings = EncoderSettings(**meta['settings'])
  except (KeyError, TypeError) as e:
    raise ValueError(f'{path}: not an encoder description ({e})') from None
  return unflatten(flat), settings, meta


def check(params, source: str):
  """Refuses encoder variables that do not fit the described network."""
  want = jax.eval_shape(module(params).init, jax.random.key(0),
                        jnp.zeros((1,) + params.sensor.shape))
  shape = lambda t: jax.tree.map(lambda v: tuple(np.shape(v)), t)
  if shape(want) != shape(params.encoder):
    raise ValueError(f'{source}: the encoder does not fit this generator (latent '
                     f'{params.latent_dim}, sensor {params.sensor.shape}, '
                     f'{params.encoder_settings}); retrain it with `{TRAIN_COMMAND}`')
