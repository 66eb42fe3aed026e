"""DUSty generator and discriminator (the paper's Table I), Flax linen.

Shapes come from the sensor: the first generator kernel and the last
discriminator kernel are H/16 x W/16. Every layer uses the equalized learning
rate: weights are drawn N(0, 1) and scaled at run time by a per-layer
constant (the sqrt(2) gain of leaky ReLU is applied after the activation, as
in the authors' code). Two choices of the constant (``eqlr``):
  * ``'authors'`` (default): 1/sqrt(weight[0].numel()) of the authors'
    PyTorch weight, as their ``EqualLR`` wrapper computes it. For transposed
    convolutions that is Cout * k * k (the latent projection: Cout * H/16 *
    W/16), and their output heads are separate layers per output ('depth',
    'confidence'), each with its own constant. The head kernel is stored
    here as one (4, 4, Cin, C) array; the per-channel scale gives the
    function of their separate heads exactly.
  * ``'fan_in'``: 1/sqrt(number of inputs each output sees): latent_dim for
    the projection, 4 * Cin for a stride-2 transposed 4x4 conv. Relative to
    'authors' the projection's constant is x8, up1-up3 x1.41 and the heads
    x0.25 (DUSty-II confidence x0.354) at the paper's size; with Adam each
    layer's effective learning rate scales with its constant.
The discriminator's constants are the true fan-in in both (for a forward
convolution weight[0].numel() is the fan-in).

Models:
  * ``baseline``: 1 output channel, tanh inverse depth; the scan is x_tilde.
  * ``dusty1``: + a measurability logit, pixel-level Gumbel-sigmoid mask.
  * ``dusty2``: + an image-level logit; masks multiplied, image-level noise
    off at test time.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from dusty_jax import configs, gumbel, layers
from dusty_jax.codec import ALPHA
from dusty_jax.sensor import SensorSpec

MODELS = {'baseline': 1, 'dusty1': 2, 'dusty2': 3}  # output channels.
DOWNSAMPLE = 16  # four stride-2 stages.
EQLR = ('authors', 'fan_in')


def check_shape(sensor: SensorSpec):
  h, w = sensor.shape
  if h % DOWNSAMPLE or w % DOWNSAMPLE:
    raise ValueError(f'sensor {sensor.name!r}: H and W must be multiples of '
                     f'{DOWNSAMPLE} for this network, got {h}x{w}')
  return h // DOWNSAMPLE, w // DOWNSAMPLE


def _normal(key, shape, dtype=jnp.float32):
  return jax.random.normal(key, shape, dtype)


def check_eqlr(eqlr: str) -> str:
  if eqlr not in EQLR:
    raise ValueError(f'unknown eqlr {eqlr!r}; known: {list(EQLR)}')
  return eqlr


def up_scale(cin: int, groups, eqlr: str):
  """Per-output-channel eq-lr constants of a 4x4 stride-2 transposed conv.

  ``groups``: output channels of each separate layer (the authors' heads are
  one layer per output; a hidden layer is one group).
  """
  if check_eqlr(eqlr) == 'fan_in':
    return jnp.full((sum(groups),), 1.0 / math.sqrt(4 * cin))
  return jnp.concatenate([jnp.full((g,), 1.0 / math.sqrt(16 * g)) for g in groups])


class EqualConv(nn.Module):
  """4x4 stride-2 conv (``up`` transposed or down), no bias, eq-lr.

  ``groups`` (transposed only): output channels of each separate layer the
  authors would use, which sets their eq-lr constants (see module doc).
  """
  features: int
  up: bool
  impl: str
  eqlr: str = 'authors'
  groups: tuple = ()

  @nn.compact
  def __call__(self, x):
    cin = x.shape[-1]
    w = self.param('kernel', _normal, (4, 4, cin, self.features))
    if self.up:
      w = w * up_scale(cin, self.groups or (self.features,), self.eqlr)
    else:
      w = w * (1.0 / math.sqrt(16 * cin))
    return (layers.conv_up if self.up else layers.conv_down)(x, w, self.impl)


def head_groups(out_channels: int) -> tuple:
  """The authors' heads: 'depth' (1 channel), then 'confidence' (the rest)."""
  return (1,) if out_channels == 1 else (1, out_channels - 1)


class Generator(nn.Module):
  sensor: SensorSpec
  out_channels: int = 2
  latent_dim: int = 512
  ch_base: int = 64
  ch_max: int = 512
  impl: str = 'matmul'
  eqlr: str = 'authors'

  def channels(self, i):
    return min(self.ch_base << i, self.ch_max)

  @nn.compact
  def __call__(self, z):
    h0, w0 = check_shape(self.sensor)
    c = self.channels(3)
    # Transposed conv of a 1x1 input with an (H/16, W/16) kernel == dense.
    w = self.param('proj', _normal, (self.latent_dim, h0 * w0 * c))
    fan = self.latent_dim if check_eqlr(self.eqlr) == 'fan_in' else h0 * w0 * c
    x = (z @ w) * (1.0 / math.sqrt(fan))
    x = x.reshape(z.shape[0], h0, w0, c)
    x = layers.leaky_act(x, self.param('proj_bias', nn.initializers.zeros, (c,)))
    for i in (2, 1, 0):
      x = EqualConv(self.channels(i), up=True, impl=self.impl, eqlr=self.eqlr,
                    name=f'up{3 - i}')(x)
      x = layers.leaky_act(
          x, self.param(f'up{3 - i}_bias', nn.initializers.zeros, (x.shape[-1],)))
    x = EqualConv(self.out_channels, up=True, impl=self.impl, eqlr=self.eqlr,
                  groups=head_groups(self.out_channels), name='head')(x)
    return x + self.param('head_bias', nn.initializers.zeros,
                          (self.out_channels,))


class Discriminator(nn.Module):
  sensor: SensorSpec
  ch_base: int = 64
  ch_max: int = 512
  impl: str = 'matmul'

  @nn.compact
  def __call__(self, x):
    """x: (B, H, W) scans -> (B,) logits."""
    h0, w0 = check_shape(self.sensor)
    x = layers.blur_vh(x[..., None])
    for i in range(4):
      c = min(self.ch_base << i, self.ch_max)
      x = EqualConv(c, up=False, impl=self.impl, name=f'down{i}')(x)
      x = layers.leaky_act(x, self.param(f'down{i}_bias', nn.initializers.zeros, (c,)))
    x = x.reshape(x.shape[0], -1)
    w = self.param('out', _normal, (x.shape[-1], 1))
    b = self.param('out_bias', nn.initializers.zeros, (1,))
    return ((x @ w) * (1.0 / math.sqrt(x.shape[-1])) + b)[:, 0]


def compose(model: str, raw, key, tau: float = 1.0, train: bool = True,
            drop_const: float = ALPHA):
  """Generator output (B, H, W, C) -> dict of what the scan is made of.

  Returns ``inv_depth`` (x_tilde, complete), ``logit`` (measurability logits,
  (B, H, W) for dusty1, (B, H, W, 2) pixel/image for dusty2), ``mask`` (the
  sampled binary mask) and ``scan`` (x = m * x_tilde + (1 - m) * drop_const;
  the authors' and the codec's drop constant is ALPHA = -1).
  """
  inv = jnp.tanh(raw[..., 0])
  if model == 'baseline':
    return {'inv_depth': inv, 'scan': inv, 'mask': jnp.ones_like(inv)}
  kp, ki = jax.random.split(key)
  if model == 'dusty1':
    logit = raw[..., 1]
    mask = gumbel.pixel_mask(kp, logit, tau)
  elif model == 'dusty2':
    logit = raw[..., 1:3]
    mask = (gumbel.pixel_mask(kp, logit[..., 0], tau) *
            gumbel.image_mask(ki, logit[..., 1], tau, train))
  else:
    raise ValueError(f'unknown model {model!r}; known: {sorted(MODELS)}')
  scan = mask * inv + (1.0 - mask) * drop_const
  return {'inv_depth': inv, 'logit': logit, 'mask': mask, 'scan': scan}


def compose_per_example(model: str, raw, keys, tau: float = 1.0,
                        train: bool = True, drop_const: float = ALPHA):
  """:func:`compose` with one key per example, so results do not depend on
  how a batch is split across devices."""
  out = jax.vmap(lambda r, k: compose(model, r[None], k, tau, train, drop_const))(
      raw, keys)
  return jax.tree.map(lambda v: v[:, 0], out)


def measurability(model: str, logit) -> Any:
  """Probability that each pixel returns a point (test-time, noise-free)."""
  if model == 'dusty1':
    return jax.nn.sigmoid(logit)
  if model == 'dusty2':
    return jax.nn.sigmoid(logit[..., 0]) * (logit[..., 1] > 0)
  raise ValueError(f'model {model!r} has no measurability map')


@dataclasses.dataclass(frozen=True)
class ModelSettings:
  """Everything that decides the networks and the generator's function, as
  one frozen value: the trainer, a trained generator and its files share it."""
  model: str = 'dusty1'
  latent_dim: int = 512
  ch_base: int = 64
  ch_max: int = 512
  eqlr: str = 'authors'
  tau: float = 1.0

  def __post_init__(self):
    if self.model not in MODELS:
      raise ValueError(f'unknown model {self.model!r}; known: {sorted(MODELS)}')
    check_eqlr(self.eqlr)
    for f in ('latent_dim', 'ch_base', 'ch_max'):
      v = getattr(self, f)
      if not isinstance(v, int) or v < 1:
        raise ValueError(f'{f}={v!r}: must be a whole number >= 1')
    if not self.tau > 0:
      raise ValueError(f'tau={self.tau!r}: the Gumbel temperature must be > 0')

  @classmethod
  def from_config(cls, config) -> 'ModelSettings':
    """From a training config (fields a config predates take legacy values)."""
    return cls(model=config.model, latent_dim=int(config.latent_dim),
               ch_base=int(config.ch_base), ch_max=int(config.ch_max),
               eqlr=configs.legacy_get(config, 'eqlr'), tau=float(config.tau))

  def generator(self, sensor: SensorSpec, impl: str | None = None) -> Generator:
    check_shape(sensor)
    return Generator(sensor, MODELS[self.model], self.latent_dim, self.ch_base,
                     self.ch_max, impl or layers.default_impl(), self.eqlr)

  def discriminator(self, sensor: SensorSpec, impl: str | None = None) -> 'Discriminator':
    check_shape(sensor)
    return Discriminator(sensor, self.ch_base, self.ch_max, impl or layers.default_impl())
