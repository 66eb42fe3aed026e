"""The encoder that starts GAN inversion: one forward pass, scan -> latent.

Beyond the paper (its inversion, like the authors' code, searches from a
random latent for 1000 Adam steps). :class:`Encoder` maps a scan
(normalised inverse depth, drops at ALPHA, corrupted or not) to a latent on
the generator's sphere of radius sqrt(d) (:func:`encode`);
``invert(params, scan, init='encoder', num_steps=k)`` refines that with k
steps of the search, and ``num_steps=0`` returns the encoder's answer alone.

An encoder belongs to one generator: it is trained on that generator's
samples (encoder_trainer.py, ``python -m dusty_jax.tools.train_encoder``)
and travels with it (generator.py: ``encoder.npz`` in a run directory,
``encoder/`` inside an exported ``.npz``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from dusty_jax import codec, errors, layers
from dusty_jax.codec import ALPHA
from dusty_jax.models import EqualConv, check_shape, pad_rows

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
    scan = pad_rows(scan, self.sensor)  # rows of no-returns up to a multiple of 16
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
  return _encode(params, scans, impl)


@functools.partial(jax.jit, static_argnames=('impl',))
def _encode(params, scans, impl):
  return project(module(params, impl).apply(params.encoder, scans))


def init_variables(key, params, settings: EncoderSettings = EncoderSettings()):
  """Fresh encoder variables for the generator ``params``."""
  enc = Encoder(params.sensor, params.latent_dim, settings, layers.default_impl())
  return jax.jit(enc.init)(key, jnp.zeros((1,) + params.sensor.shape))
