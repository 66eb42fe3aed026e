"""DUSty generator and discriminator (the paper's Table I), Flax linen.

Shapes come from the sensor: the first generator kernel and the last
discriminator kernel are H/16 x W/16 (H rounded up: :func:`check_shape`). Every layer uses the equalized learning
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

Model variants (``VARIANTS``, looked up by name with :func:`get_variant`;
nothing outside this file compares their names):
  * ``baseline``: 1 output channel, tanh inverse depth; the scan is x_tilde.
  * ``dusty1``: + a measurability logit, pixel-level Gumbel-sigmoid mask.
  * ``dusty2``: + an image-level logit; masks multiplied, image-level noise
    off at test time.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import flax.linen as nn
import jax
import jax.numpy as jnp

from dusty_jax import gumbel, layers, levels as levels_lib
from dusty_jax.codec import ALPHA
from dusty_jax.sensor import SensorSpec

DOWNSAMPLE = 16  # four stride-2 stages.
EQLR = ('authors', 'fan_in')


def check_shape(sensor: SensorSpec):
  """(H/16, W/16) rounded up: the networks' coarsest grid for ``sensor``.

  Any number of rows works: the networks run on the rows rounded up to a
  multiple of 16 (:func:`pad_rows`); the generator's extra rows are cut off
  before anything reads its outputs, and the rows the discriminator and the
  encoder get added are no-returns (ALPHA), for real and generated scans
  alike. A width must be a multiple of 16: columns are the circle, and a
  padded column would be a seam."""
  h, w = sensor.shape
  if w % DOWNSAMPLE:
    near = max(DOWNSAMPLE, DOWNSAMPLE * round(w / DOWNSAMPLE))
    raise ValueError(f'sensor {sensor.name!r}: W must be a multiple of {DOWNSAMPLE} '
                     f'for this network, got {h}x{w}; the nearest valid width is '
                     f'{near} (--config.sensor.width={near})')
  return -(-h // DOWNSAMPLE), w // DOWNSAMPLE


def pad_rows(x, sensor: SensorSpec, multiple: int = DOWNSAMPLE, value=ALPHA):
  """(B, H, W, ...) -> (B, H', W, ...), H' = H rounded up to ``multiple``:
  rows of ``value`` below the sensor's lowest beam (none where H is a multiple)."""
  extra = -sensor.shape[0] % multiple
  if not extra:
    return x
  return jnp.pad(x, [(0, 0), (0, extra)] + [(0, 0)] * (x.ndim - 2), constant_values=value)


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


class Generator(nn.Module):
  sensor: SensorSpec
  head_groups: tuple = (1, 1)  # output channels of each head (Variant.head_groups)
  latent_dim: int = 512
  ch_base: int = 64
  ch_max: int = 512
  impl: str = 'matmul'
  eqlr: str = 'authors'
  # One logit offset per row added to the pixel measurability (channel 1):
  # a LiDAR's lasers each have their own sensitivity, and a conv net with
  # circular padding sees little of which row it is on.
  ring_bias: bool = False
  # One logit offset per (ring, depth) cell of x_tilde, fitted after training
  # (levels.py): how many pixels drop at each range of each laser.
  depth_levels: bool = False

  out_channels = property(lambda self: sum(self.head_groups))

  def channels(self, i):
    return min(self.ch_base << i, self.ch_max)

  @nn.compact
  def __call__(self, z, detached_head: bool = False):
    """Raw outputs (B, H, W, C). With ``detached_head`` also the outputs of
    the same head (its kernel, bias and ring offsets) on the trunk's
    features under stop_gradient: equal values, whose gradient reaches the
    head alone (drops.rate_head_only)."""
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
    head = EqualConv(self.out_channels, up=True, impl=self.impl, eqlr=self.eqlr,
                     groups=self.head_groups, name='head')
    bias = self.param('head_bias', nn.initializers.zeros, (self.out_channels,))
    h = self.sensor.shape[0]
    rows = self.param('ring_bias', nn.initializers.zeros, (h,)) if self.ring_bias else None
    cells = (self.param('depth_levels', nn.initializers.zeros, (h, levels_lib.BINS))
             if self.depth_levels else None)
    def out(features):
      y = head(features)
      y = (y[:, :h] if y.shape[1] > h else y) + bias  # the sensor's rows (check_shape)
      if rows is not None:
        y = y.at[..., 1].add(rows[:, None])
      if cells is not None:  # x_tilde as Variant.decode_inv_depth makes it
        index = levels_lib.of_x_tilde(jnp.tanh(y[..., 0]), self.sensor)
        y = y.at[..., 1].add(cells.reshape(-1)[index])
      return y
    return (out(x), out(jax.lax.stop_gradient(x))) if detached_head else out(x)


class Discriminator(nn.Module):
  sensor: SensorSpec
  ch_base: int = 64
  ch_max: int = 512
  impl: str = 'matmul'

  @nn.compact
  def __call__(self, x):
    """x: (B, H, W) scans, or (B, H, W, C) with more channels -> (B,) logits."""
    check_shape(self.sensor)
    x = pad_rows(x, self.sensor)
    x = layers.blur_vh(x[..., None] if x.ndim == 3 else x)
    for i in range(4):
      c = min(self.ch_base << i, self.ch_max)
      x = EqualConv(c, up=False, impl=self.impl, name=f'down{i}')(x)
      x = layers.leaky_act(x, self.param(f'down{i}_bias', nn.initializers.zeros, (c,)))
    x = x.reshape(x.shape[0], -1)
    w = self.param('out', _normal, (x.shape[-1], 1))
    b = self.param('out_bias', nn.initializers.zeros, (1,))
    return ((x @ w) * (1.0 / math.sqrt(x.shape[-1])) + b)[:, 0]


def _pixel_mask(key, logit, tau, train):
  del train
  kp, _ = jax.random.split(key)
  return gumbel.pixel_mask(kp, logit, tau)


def _pixel_image_mask(key, logit, tau, train):
  kp, ki = jax.random.split(key)
  return (gumbel.pixel_mask(kp, logit[..., 0], tau) *
          gumbel.image_mask(ki, logit[..., 1], tau, train))


@dataclasses.dataclass(frozen=True)
class Variant:
  """What one model variant is: its output heads, how its outputs make a
  scan, its measurability, and how the authors' weights map onto it.

  Attributes:
    name: its name in configs and ``VARIANTS``.
    heads: (head, channels) of the generator's output, in channel order;
      the head names are the authors' ('depth', 'confidence').
    logit: raw output (B, H, W, C) -> the measurability logits, or None
      (no measurability: every pixel returns a point).
    sample_mask: (key, logit, tau, train) -> the sampled binary mask.
    probability: logit -> the test-time (noise-free) probability of a return.
    authors_arch: the masker part of the authors' generator ``arch``
      ('none/dcgan_eqlr', ...).
    authors_prefix: the prefix of the authors' generator state-dict keys.
  """
  name: str
  heads: tuple
  logit: Callable | None = None
  sample_mask: Callable | None = None
  probability: Callable | None = None
  authors_arch: str = ''
  authors_prefix: str = ''

  @property
  def out_channels(self) -> int:
    return sum(c for _, c in self.heads)

  @property
  def head_groups(self) -> tuple:
    """Output channels of each of the authors' separate head layers."""
    return tuple(c for _, c in self.heads)

  @property
  def has_measurability(self) -> bool:
    return self.logit is not None

  def decode_inv_depth(self, raw):
    """x_tilde, the complete inverse depth in [-1, 1], of raw outputs."""
    return jnp.tanh(raw[..., 0])

  def compose(self, raw, key, tau: float = 1.0, train: bool = True):
    """Generator output (B, H, W, C) -> dict of what the scan is made of.

    Returns ``inv_depth`` (x_tilde, complete), ``logit`` (measurability
    logits, (B, H, W) for dusty1, (B, H, W, 2) pixel/image for dusty2;
    absent without a measurability), ``mask`` (the sampled binary mask) and
    ``scan`` (x = m * x_tilde + (1 - m) * ALPHA; ALPHA = -1 is the authors'
    drop_const and the codec's).
    """
    inv = self.decode_inv_depth(raw)
    if not self.has_measurability:
      return {'inv_depth': inv, 'scan': inv, 'mask': jnp.ones_like(inv)}
    logit = self.logit(raw)
    mask = self.sample_mask(key, logit, tau, train)
    scan = mask * inv + (1.0 - mask) * ALPHA
    return {'inv_depth': inv, 'logit': logit, 'mask': mask, 'scan': scan}

  def compose_per_example(self, raw, keys, tau: float = 1.0, train: bool = True):
    """:meth:`compose` with one key per example, so results do not depend
    on how a batch is split across devices."""
    out = jax.vmap(lambda r, k: self.compose(r[None], k, tau, train))(raw, keys)
    return jax.tree.map(lambda v: v[:, 0], out)

  def measurability(self, logit) -> Any:
    """Probability that each pixel returns a point (test-time, noise-free)."""
    if not self.has_measurability:
      raise ValueError(f'model {self.name!r} has no measurability map')
    return self.probability(logit)

  def measurability_of(self, out: dict):
    """:meth:`measurability` of a :meth:`compose` result; all ones for a
    variant without one."""
    if not self.has_measurability:
      return jnp.ones_like(out['inv_depth'])
    return self.measurability(out['logit'])


VARIANTS = {
    'baseline': Variant('baseline', (('depth', 1),), authors_arch='none'),
    'dusty1': Variant('dusty1', (('depth', 1), ('confidence', 1)),
                      logit=lambda raw: raw[..., 1], sample_mask=_pixel_mask,
                      probability=jax.nn.sigmoid, authors_arch='dusty1',
                      authors_prefix='backbone.'),
    'dusty2': Variant('dusty2', (('depth', 1), ('confidence', 2)),
                      logit=lambda raw: raw[..., 1:3], sample_mask=_pixel_image_mask,
                      probability=lambda l: jax.nn.sigmoid(l[..., 0]) * (l[..., 1] > 0),
                      authors_arch='dusty2', authors_prefix='backbone.'),
}


def get_variant(name: str) -> Variant:
  """The model variant of that name; ValueError naming the known ones."""
  try:
    return VARIANTS[name]
  except (KeyError, TypeError):
    raise ValueError(f'unknown model {name!r}; known: {sorted(VARIANTS)}') from None


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
  # Beyond the paper (config drops.ring_bias): the pixel measurability logit
  # gets one learned offset per ring, i.e. per laser of the sensor (started
  # at the training data's keep rate per ring: drops.init_biases).
  ring_bias: bool = False
  # After training (levels.py): one offset per (ring, depth) cell of x_tilde.
  depth_levels: bool = False

  def __post_init__(self):
    get_variant(self.model)
    check_eqlr(self.eqlr)
    for f in ('latent_dim', 'ch_base', 'ch_max'):
      v = getattr(self, f)
      if not isinstance(v, int) or v < 1:
        raise ValueError(f'{f}={v!r}: must be a whole number >= 1')
    gumbel.check_tau(self.tau)

  @property
  def variant(self) -> Variant:
    return get_variant(self.model)

  def generator(self, sensor: SensorSpec, impl: str | None = None) -> Generator:
    check_shape(sensor)
    for f in ('ring_bias', 'depth_levels'):
      if getattr(self, f) and not self.variant.has_measurability:
        raise ValueError(f'{f}: the {self.model} model has no measurability')
    return Generator(sensor, self.variant.head_groups, self.latent_dim, self.ch_base,
                     self.ch_max, impl or layers.default_impl(), self.eqlr,
                     self.ring_bias, self.depth_levels)

  def discriminator(self, sensor: SensorSpec, impl: str | None = None) -> 'Discriminator':
    check_shape(sensor)
    return Discriminator(sensor, self.ch_base, self.ch_max, impl or layers.default_impl())
