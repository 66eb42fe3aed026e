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
  * G: non-saturating loss through the updated D. The generator's forward
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

from dusty_jax import (augment, checkpoint, codec, configs, errors, generator, losses,
                       models, parallel, sampling, writers)
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


@dataclasses.dataclass(frozen=True)
class DropOptions:
  """Point-drop mechanisms beyond the paper (config ``drops``; all off by
  default, which trains as the authors do).

  * ``mask_channel`` w > 0: the discriminator sees a second channel, the
    keep-mask times w (real: the returns; fake: the straight-through
    Gumbel mask, so G's measurability gets D's gradient directly, not only
    through x_tilde - drop_const). ``mask_noise``: Gaussian noise of this
    std on that channel; ``mask_dropout``: per example, the channel is
    hidden (zeroed) with this probability. R1 covers both channels.
  * ``keep_drops``: DiffAugment keeps drops as drops (augment.with_mask).
  * ``mask_bias``: the measurability logit's initial bias (the authors' is
    0: half the pixels dropped at the start); logit(keep rate) starts at
    the data's rate.
  * ``mask_lr``: multiplies the Adam updates of the measurability head.
  * ``rate_weight`` lambda: G's loss + lambda (mean keep - real keep)^2,
    over the batch (``rate_by='image'``) or per row (``'ring'``, averaged
    over rows), real keep rates from this step's real batch. ``'ring_depth'``:
    per (ring, depth bin) cell, the depth judged from the returned
    neighbours alike in real and generated scans (neighbour_depth_bin), so
    the drops may depend on the range within a ring, as a sensor's do.
    ``rate_shrink`` k: each cell's real rate is shrunk towards its ring's,
    (kept + k * ring rate) / (n + k) (cell_rate_penalty). The tallies are
    the global batch's: N devices compute what one does.
    ``rate_head_only``: the rate term is taken on the expected keep rate
    (the measurability, not the sampled mask) of the head applied to the
    trunk's features under stop_gradient, so it trains the measurability
    head and its biases and leaves G's shared trunk to the GAN loss alone.
  * ``mask_detached``: the measurability channels come from the head on
    the trunk's features under stop_gradient (the same values), so no
    gradient of the mask (the GAN loss's straight-through one, the rate
    term's) reaches G's shared trunk: the trunk learns from x_tilde alone,
    the head's measurability kernel and biases from the mask.
  * ``depth_weight`` mu: G's loss + mu * the mean over rings of the squared
    gap between the mean returned value (normalised inverse depth) of the
    generated and of the real scans in that ring (depth_penalty; the
    global batch's tallies). Its gradient reaches x_tilde at the kept
    pixels only; the keep-masks weigh, they are not differentiated. It
    anchors the scene's range where a G that cannot place its drops where
    D expects them would hide them instead, by moving surfaces farther
    away, where a drop differs little from a return (README "Depth that
    survives the drops").
  * ``dip_weight`` nu: G's loss + nu * the mean depth of the dips among the
    generated returns: each returned pixel with both ring neighbours
    returned that lies farther than both by more than DIP (normalised
    inverse depth), by how much (dip_penalty; the neighbours are not
    differentiated, so a dip is filled, not its neighbours lowered).
    Variants that keep their drops grow such dips, a checkerboard of far
    pixels that looks like drops to D; real surfaces hardly ever have them.
  * ``peak_weight`` rho: G's loss + rho * how far the mean height of the
    peaks among the generated returns (each pixel nearer than both ring
    neighbours by more than DIP, by how much) exceeds the real batch's
    (peak_penalty). Real scans have peaks (poles, trunks): only the excess,
    a lattice of near pixels, is paid for.
  * ``far_weight`` phi: G's loss + phi * the mean over rings of the squared
    gap between the share of the generated pixels that are returns beyond
    FAR_M (40 m) and the real batch's (far_penalty). A pixel is far by its
    own complete depth x_tilde (not differentiated), and the keep values
    are differentiated (the head's expected keep with rate_head_only), so
    the term moves drops, not surfaces. The scans' far structure (sky-like
    surfaces the sensor hardly returns) otherwise comes back as returns:
    the synthesis MMD gap lies there (benchmarks/far_returns.py).
    ``rate_skip_far``: the ring_depth rate term leaves out its cells beyond
    FAR_M, whose high real keep rate otherwise holds far regions kept.
  * ``ring_bias`` (config drops.ring_bias; it is part of the model, so it
    lives in ModelSettings, not here): G's pixel measurability gets a
    learned logit offset per ring, started at the training data's keep rate
    of that ring (init_state's ``ring_keep``).
  """
  mask_channel: float = 0.0
  mask_noise: float = 0.0
  mask_dropout: float = 0.0
  keep_drops: bool = False
  mask_bias: float = 0.0
  mask_lr: float = 1.0
  rate_weight: float = 0.0
  rate_by: str = 'image'
  rate_shrink: float = 0.0
  rate_head_only: bool = False
  mask_detached: bool = False
  depth_weight: float = 0.0
  dip_weight: float = 0.0
  peak_weight: float = 0.0
  far_weight: float = 0.0
  rate_skip_far: bool = False

  @classmethod
  def from_config(cls, config) -> 'DropOptions':
    d = config.drops  # validated, or translated by configs.load
    return cls(mask_channel=float(d.mask_channel), mask_noise=float(d.mask_noise),
               mask_dropout=float(d.mask_dropout), keep_drops=bool(d.keep_drops),
               mask_bias=float(d.mask_bias), mask_lr=float(d.mask_lr),
               rate_weight=float(d.rate_weight), rate_by=str(d.rate_by),
               rate_shrink=float(d.rate_shrink),
               rate_head_only=bool(d.rate_head_only),
               mask_detached=bool(d.mask_detached),
               depth_weight=float(d.depth_weight), dip_weight=float(d.dip_weight),
               peak_weight=float(d.peak_weight), far_weight=float(d.far_weight),
               rate_skip_far=bool(d.rate_skip_far))

  @property
  def d_sees_mask(self) -> bool:
    """The discriminator's input carries the keep-mask (as a channel, or as
    drops an augmentation must keep)."""
    return self.mask_channel > 0 or self.keep_drops

  @property
  def g_needs_mask(self) -> bool:
    """G's loss differentiates the mask itself (not only the scan)."""
    return self.mask_channel > 0 or self.rate_weight > 0 or self.far_weight > 0


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
  drop_const: float = static()
  drops: DropOptions = static()


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
      drop_const=float(config.drop_const), drops=DropOptions.from_config(config))


def init_state(setup: Setup, key, ring_keep=None) -> TrainState:
  """Fresh networks and optimisers. ``ring_keep``: (H,) the training data's
  keep rate per ring, where the model has a ring bias (drops.ring_bias): the
  measurability starts at it (without it, the ring offsets start at 0)."""
  kg, kd = jax.random.split(key)
  z = jnp.zeros((1, setup.settings.latent_dim))
  g_params = jax.jit(setup.generator.init)(kg, z)
  if setup.drops.mask_bias:
    g_params = set_mask_bias(g_params, setup.drops.mask_bias)
  if setup.settings.ring_bias and ring_keep is not None:
    g_params = set_ring_bias(g_params, ring_keep, setup.drops.mask_bias)
  channels = (2,) if setup.drops.mask_channel > 0 else ()
  d_params = jax.jit(setup.discriminator.init)(
      kd, jnp.zeros((1,) + setup.sensor.shape + channels))
  return TrainState(step=jnp.zeros((), jnp.int32), g_params=g_params,
                    d_params=d_params, g_opt=setup.g_tx.init(g_params),
                    d_opt=setup.d_tx.init(d_params),
                    ema_params=jax.tree.map(jnp.copy, g_params))


def set_mask_bias(g_params, bias: float):
  """G's variables with the pixel measurability logit's bias set to ``bias``
  (head channel 1; DUSty-II's image-level logit is left alone)."""
  p = flax.core.unfreeze(g_params) if hasattr(g_params, 'unfreeze') else g_params
  head_bias = p['params']['head_bias'].at[1].set(bias)
  return {**p, 'params': {**p['params'], 'head_bias': head_bias}}


RING_KEEP_CLIP = 0.01  # keep rates start within [0.01, 0.99]: finite logits.


def ring_keep_rate(depth, sensor, num: int = 1024) -> np.ndarray:
  """(H,) the fraction of returned pixels per ring over the first ``num``
  scans of ``depth`` (metric, 0 or out of range: dropped)."""
  d = np.asarray(depth[:num], np.float32)
  if not len(d):
    raise ValueError('ring_keep_rate: no scans to count returns in')
  return np.asarray(codec.valid_depth(d, sensor), np.float64).mean(axis=(0, 2))


def set_ring_bias(g_params, ring_keep, mask_bias: float = 0.0):
  """G's variables with the per-ring measurability offsets set so that,
  with the global logit ``mask_bias``, ring r starts at logit(ring_keep[r])."""
  p = flax.core.unfreeze(g_params) if hasattr(g_params, 'unfreeze') else g_params
  keep = np.clip(np.asarray(ring_keep, np.float64), RING_KEEP_CLIP, 1 - RING_KEEP_CLIP)
  rows = p['params']['ring_bias']
  if keep.shape != rows.shape:
    raise ValueError(f'ring_keep has shape {keep.shape}; the sensor has {rows.shape[0]} rings')
  logit = np.log(keep) - np.log1p(-keep) - mask_bias
  return {**p, 'params': {**p['params'], 'ring_bias': jnp.asarray(logit, rows.dtype)}}


def scale_mask_updates(updates, factor: float):
  """Multiplies the updates of the measurability head (head channels >= 1)."""
  params = updates['params']
  scale = jnp.ones(params['head_bias'].shape).at[1:].set(factor)
  return {**updates, 'params': {**params, 'head': {'kernel': params['head']['kernel'] * scale},
                                'head_bias': params['head_bias'] * scale}}


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
  out = variant.compose_per_example(raw, keys, setup.settings.tau, train, setup.drop_const)
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
  """What D sees of scans ``x``: DiffAugmented; ``x`` may be a pair (scans,
  keep-masks) when point-drop options are on (:func:`d_view`)."""
  if isinstance(x, tuple):
    return d_view(setup, keys, *x)
  return augment.per_example(keys, x, setup.policy, setup.augment_style)


def d_view(setup: Setup, keys, scan, keep):
  """D's input for scans (B, H, W) and their keep-masks under DropOptions:
  (B, H, W), or (B, H, W, 2) with the mask channel."""
  drops = setup.drops
  if not drops.d_sees_mask:
    return augment.per_example(keys, scan, setup.policy, setup.augment_style)
  x, keep = augment.per_example_with_mask(keys, scan, keep, setup.policy,
                                          setup.augment_style, drops.keep_drops,
                                          setup.drop_const)
  if drops.mask_channel <= 0:
    return x
  channel = drops.mask_channel * keep
  # Draws of their own, from the augmentation keys (not reused as they are).
  extra = jax.vmap(lambda k: jax.random.split(jax.random.fold_in(k, 1)))(keys)
  if drops.mask_noise > 0:
    channel = channel + drops.mask_noise * jax.vmap(
        lambda k: jax.random.normal(k, scan.shape[1:]))(extra[:, 0])
  if drops.mask_dropout > 0:
    hide = jax.vmap(lambda k: jax.random.bernoulli(k, drops.mask_dropout))(extra[:, 1])
    channel = jnp.where(hide[:, None, None], 0.0, channel)
  return jnp.stack([x, channel], axis=-1)


def _psum(x, axis_name):
  return x if axis_name is None else lax.psum(x, axis_name)


def rate_penalty(drops: DropOptions, keep, real_keep, axis_name=None):
  """(generated keep rate - real keep rate)^2: of the whole batch, or per
  row (averaged over rows) with ``rate_by='ring'``. With ``axis_name`` the
  rates are those of the global batch (the tallies are summed over the
  devices), so N devices compute what one device does with the same batch."""
  axes = (0, 2) if drops.rate_by == 'ring' else (0, 1, 2)
  n = _psum(np.prod([keep.shape[a] for a in axes]), axis_name)
  rate = lambda k: _psum(k.sum(axis=axes), axis_name) / n
  gap = rate(keep) - lax.stop_gradient(rate(real_keep))
  return jnp.mean(jnp.square(gap))


def ring_depth_gap(scan, real, axis_name=None):
  """(H,) the mean returned value of each row of ``scan`` (B, H, W; a
  return is > ALPHA) minus that of ``real``; 0 for a row without returns on
  either side. With ``axis_name`` the tallies are the global batch's. The
  masks are not differentiated: the gradient reaches the returned values."""
  def row_mean(x):
    keep = lax.stop_gradient((x > codec.ALPHA).astype(x.dtype))
    n = _psum(keep.sum(axis=(0, 2)), axis_name)
    return _psum((x * keep).sum(axis=(0, 2)), axis_name) / jnp.maximum(n, 1.0), n
  fake_mean, n_fake = row_mean(scan)
  real_mean, n_real = row_mean(lax.stop_gradient(real))
  return jnp.where((n_fake > 0) & (n_real > 0), fake_mean - real_mean, 0.0)


def depth_penalty(scan, real, axis_name=None):
  """``depth_weight``'s term: the mean over rows of ring_depth_gap squared."""
  return jnp.mean(jnp.square(ring_depth_gap(scan, real, axis_name)))


DIP = 0.05  # normalised inverse depth: how far behind both ring neighbours a dip lies


def _ring_outliers(scan, sign, margin):
  """(amounts, counted): per pixel of ``scan`` (B, H, W), how far it lies
  beyond both ring neighbours by more than ``margin``, behind them (``sign``
  -1: a dip) or in front of them (+1: a peak), 0 if not; and whether it and
  both neighbours are returns (> ALPHA; the ring wraps around). The
  neighbours and the masks are not differentiated."""
  keep = lax.stop_gradient(scan > codec.ALPHA)
  left, right = jnp.roll(scan, 1, -1), jnp.roll(scan, -1, -1)
  bound = lax.stop_gradient(jnp.maximum(left, right) if sign > 0 else jnp.minimum(left, right))
  counted = keep & jnp.roll(keep, 1, -1) & jnp.roll(keep, -1, -1)
  return jnp.where(counted, jax.nn.relu(sign * (scan - bound) - margin), 0.0), counted


def dips(scan, dip: float = DIP):
  """(depths, counted): per pixel of ``scan`` (B, H, W), how far it lies
  behind both ring neighbours beyond ``dip`` (0 if not), and whether it and
  both neighbours are returns (> ALPHA; the ring wraps around). The
  neighbours and the masks are not differentiated."""
  return _ring_outliers(scan, -1, dip)


def peaks(scan, peak: float = DIP):
  """(heights, counted): as ``dips``, for pixels in front of both ring
  neighbours beyond ``peak``: thin near objects (poles, trunks) in real
  scans, a lattice of near pixels in generated ones."""
  return _ring_outliers(scan, 1, peak)


def _share(outliers, scan, axis_name=None):
  amount, counted = outliers(scan)
  return _psum((amount > 0).sum(), axis_name) / jnp.maximum(_psum(counted.sum(), axis_name), 1)


def _mean_amount(outliers, scan, axis_name=None):
  amount, counted = outliers(scan)
  return _psum(amount.sum(), axis_name) / jnp.maximum(_psum(counted.sum(), axis_name), 1)


def _dip_share(scan, axis_name=None):
  return _share(dips, scan, axis_name)


def dip_penalty(scan, axis_name=None):
  """``dip_weight``'s term: the mean dip depth over the counted pixels (the
  global batch's with ``axis_name``)."""
  return _mean_amount(dips, scan, axis_name)


def peak_penalty(scan, real, axis_name=None):
  """``peak_weight``'s term: how far the mean peak height over the counted
  pixels of ``scan`` exceeds the real batch's (0 if it does not; the global
  batches' with ``axis_name``). Real scans have peaks, their poles and
  trunks, so G keeps as many as they have and pays for the excess only."""
  excess = _mean_amount(peaks, scan, axis_name) - lax.stop_gradient(
      _mean_amount(peaks, real, axis_name))
  return jax.nn.relu(excess)


FAR_M = 40.0  # metres: a return beyond this is far (far_weight, far_share)


def _far(x, sensor: SensorSpec):
  """Pixels of (B, H, W) normalised inverse depth farther than FAR_M (and
  not a drop: > ALPHA); not differentiated."""
  x = lax.stop_gradient(x)
  return (x > codec.ALPHA) & (x <= codec.encode(jnp.float32(FAR_M), sensor))


def far_share(scan, sensor: SensorSpec, axis_name=None):
  """The share of the pixels of ``scan`` that are returns beyond FAR_M (the
  global batch's with ``axis_name``)."""
  n = _psum(np.prod(scan.shape), axis_name)
  return _psum(_far(scan, sensor).sum(), axis_name) / n


def far_penalty(sensor: SensorSpec, keep, inv_depth, real, axis_name=None):
  """``far_weight``'s term: the mean over rows of the squared gap between
  the share of generated pixels that are far returns, sum(keep x far) / n
  with far judged on the complete ``inv_depth`` (x_tilde), and the share of
  the ``real`` scans' pixels that are. Only ``keep`` is differentiated."""
  n = _psum(keep.shape[0] * keep.shape[2], axis_name)
  share = lambda a: _psum(a.sum(axis=(0, 2)), axis_name) / n
  fake = share(keep * _far(inv_depth, sensor))
  target = lax.stop_gradient(share(_far(real, sensor).astype(keep.dtype)))
  return jnp.mean(jnp.square(fake - target))


# Metric depth edges (m) of the ``rate_by='ring_depth'`` cells.
RATE_DEPTH_EDGES = (5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 60.0)
NEIGHBOURS = (1, 2)  # half-height, half-width of the neighbourhood window


def neighbour_depth_bin(scan, keep, sensor: SensorSpec, edges=RATE_DEPTH_EDGES):
  """(B, H, W) int: each pixel's depth bin, judged from its neighbours.

  The mean normalised inverse depth of the returned pixels (``keep``) in a
  (3, 5) window around each pixel, the pixel itself left out (columns wrap
  around, rows do not), binned by the metric ``edges``: bin 0 when no
  neighbour returned, then 1 (nearer than edges[0]) to len(edges) + 1
  (beyond edges[-1]). Leaving the pixel out makes the bin of a drop and of a
  return alike, so real scans, whose dropped depth is unknown, and
  generated ones are binned the same way.
  """
  keep = keep.astype(jnp.float32)
  x = jnp.where(keep > 0, scan, 0.0)
  (dh, dw), h = NEIGHBOURS, scan.shape[1]
  pad = lambda a: jnp.pad(a, ((0, 0), (dh, dh), (0, 0)))
  xs, ks = pad(x), pad(keep)
  total, count = jnp.zeros_like(x), jnp.zeros_like(x)
  for i in range(2 * dh + 1):
    for j in range(-dw, dw + 1):
      if (i, j) == (dh, 0):
        continue
      total += jnp.roll(xs[:, i:i + h], j, axis=2)
      count += jnp.roll(ks[:, i:i + h], j, axis=2)
  mean = total / jnp.maximum(count, 1.0)
  # Depth beyond an edge <=> inverse depth at or below its code.
  codes = codec.encode(jnp.asarray(edges, jnp.float32), sensor)
  far = jnp.sum(mean[..., None] <= codes, axis=-1)
  return jnp.where(count > 0, 1 + far, 0)


def cell_rate_penalty(keep, real_keep, cells, real_cells, num_cells: int,
                      shrink: float = 0.0, groups: int = 1, axis_name=None, counted=None):
  """The squared gap between the generated and the real keep rate of each
  cell of ``cells`` / ``real_cells`` (ints in [0, num_cells): one per
  pixel), weighted by the generated pixels in the cell, so each generated
  pixel is pulled towards its cell's real rate as the other rate terms pull
  it towards the ring's.

  ``shrink`` k = 0: cells empty on either side count 0. k > 0: each cell's
  target is shrunk towards its group's real rate, (kept + k * group rate) /
  (n + k), so a cell the real batch barely fills (or misses) is pulled to
  its group's rate rather than to a noisy 0 or 1. The cells form ``groups``
  consecutive equal blocks (for ring_depth: the rings). With ``axis_name``
  the tallies are the global batch's (summed over the devices).
  ``counted``: (num_cells,) bools; the cells it marks False weigh 0 (their
  pixels still count towards their group's rate).
  """
  flat = lambda a: a.reshape(-1)
  count = lambda c, w: _psum(jax.ops.segment_sum(flat(w), flat(c), num_cells), axis_name)
  ones = jnp.ones_like(keep)
  n_fake, n_real = count(cells, ones), count(real_cells, ones)
  fake_rate = count(cells, keep) / jnp.maximum(n_fake, 1.0)
  kept_real = lax.stop_gradient(count(real_cells, real_keep))
  if shrink > 0:
    by_group = lambda a: a.reshape(groups, -1).sum(axis=1, keepdims=True)
    group_rate = by_group(kept_real) / jnp.maximum(by_group(n_real), 1.0)
    real_rate = flat((kept_real.reshape(groups, -1) + shrink * group_rate) /
                     (n_real.reshape(groups, -1) + shrink))
    weight = n_fake
  else:
    real_rate = kept_real / jnp.maximum(n_real, 1.0)
    weight = jnp.where(n_real > 0, n_fake, 0.0)
  if counted is not None:
    weight = jnp.where(counted, weight, 0.0)
  return jnp.sum(weight * jnp.square(fake_rate - real_rate)) / jnp.maximum(weight.sum(), 1.0)


RATE_DEPTH_BINS = len(RATE_DEPTH_EDGES) + 2  # bin 0 (no returned neighbour) and the ranges


def ring_depth_cells(scan, keep, sensor: SensorSpec):
  """(B, H, W) int: each pixel's (ring, depth bin) cell, ring * RATE_DEPTH_BINS
  + neighbour_depth_bin; cells run over [0, H * RATE_DEPTH_BINS)."""
  bins = neighbour_depth_bin(scan, keep, sensor)
  return jnp.arange(scan.shape[1])[None, :, None] * RATE_DEPTH_BINS + bins


def ring_depth_rate_penalty(sensor: SensorSpec, fake, real, shrink: float = 0.0,
                            axis_name=None, keep=None, skip_far: bool = False):
  """``rate_by='ring_depth'``: the cell rate penalty over (ring, depth bin)
  cells, each cell's target shrunk towards its ring's rate by ``shrink``.
  ``fake`` and ``real``: (scans, keep-masks) pairs; the cells are not
  differentiated. The real rates are the training batch's (with
  ``axis_name``, summed over the devices): cells the batch barely fills give
  noisy targets, which ``shrink`` calms. ``keep``: the generated keep values
  to differentiate (default: the mask ``fake[1]``, which bins the cells).
  ``skip_far``: the cells whose depth bin lies beyond FAR_M weigh 0, so
  far_weight's term alone sets how often far pixels return."""
  cells = lambda scan, keep: ring_depth_cells(lax.stop_gradient(scan),
                                              lax.stop_gradient(keep) > 0.5, sensor)
  h = fake[0].shape[1]
  keep = fake[1] if keep is None else keep
  counted = None
  if skip_far:  # bin 0 (no returned neighbour), then bins 1.. from 0 m, edges[0], ...
    near = [True] + [start < FAR_M for start in (0.0,) + RATE_DEPTH_EDGES]
    counted = jnp.asarray(np.tile(near, h))
  return cell_rate_penalty(keep, real[1], cells(*fake), cells(*real),
                           h * RATE_DEPTH_BINS, shrink, h, axis_name, counted)


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


def g_step(setup: Setup, g_params, g_opt, d_params, fake, fake_vjp, key,
           axis_name=None, real=None):
  """One generator update through ``d_params``: (g_params, g_opt, loss_g).

  ``fake`` are the generated scans and ``fake_vjp`` the VJP of the
  generator's forward pass that made them (``jax.vjp``), so the forward pass
  of the D step serves here too (the authors reuse it the same way).
  ``key``: the augmentation keys, one per example. With point-drop options
  ``fake`` is the pair (scans, keep-masks) and ``real`` the real batch's
  (scans, keep-masks) pair (for ``rate_weight``); the returned loss is then the
  adversarial loss alone, without the rate, depth, dip or peak penalty. With ``rate_head_only``
  ``fake`` is (scans, keep-masks, keep probabilities of the detached head),
  and the rate term is taken on the third. With ``far_weight`` the tuple
  ends with the complete inverse depth x_tilde.
  """
  d_local = _local(d_params, axis_name)

  def objective(scan):
    view = scan[:2] if isinstance(scan, tuple) else scan
    adv = losses.g_loss(setup.discriminator.apply(d_local, _augment(setup, key, view)))
    total = adv
    x, x_real = (view[0], real[0]) if isinstance(view, tuple) else (view, real)  # the scans
    if setup.drops.depth_weight > 0:
      total = total + setup.drops.depth_weight * depth_penalty(x, x_real, axis_name)
    if setup.drops.dip_weight > 0:
      total = total + setup.drops.dip_weight * dip_penalty(x, axis_name)
    if setup.drops.peak_weight > 0:
      total = total + setup.drops.peak_weight * peak_penalty(x, x_real, axis_name)
    keep = None  # the keep values the drop terms differentiate
    if isinstance(scan, tuple):
      keep = scan[2] if setup.drops.rate_head_only else scan[1]
    if setup.drops.far_weight > 0:  # x_tilde is the last of the tuple
      total = total + setup.drops.far_weight * far_penalty(
          setup.sensor, keep, scan[-1], real[0], axis_name)
    if setup.drops.rate_weight == 0:
      return total, adv
    if setup.drops.rate_by == 'ring_depth':
      penalty = ring_depth_rate_penalty(setup.sensor, view, real, setup.drops.rate_shrink,
                                        axis_name, keep, setup.drops.rate_skip_far)
    else:
      penalty = rate_penalty(setup.drops, keep, real[1], axis_name)
    return total + setup.drops.rate_weight * penalty, adv

  (_, loss_g), dscan = jax.value_and_grad(objective, has_aux=True)(fake)
  (grads,) = fake_vjp(dscan)
  grads = _pmean(grads, axis_name)
  updates, g_opt = setup.g_tx.update(grads, g_opt, g_params)
  if setup.drops.mask_lr != 1.0:
    updates = scale_mask_updates(updates, setup.drops.mask_lr)
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
  # Drops in the discriminator's input take the drop constant (ALPHA: as is).
  batch = jnp.where(batch <= codec.ALPHA, setup.drop_const, batch)
  key = jax.random.fold_in(key, state.step)
  ids = lax.axis_index(axis_name) * b + jnp.arange(b)
  keys = jax.vmap(lambda i: jax.random.split(jax.random.fold_in(key, i), 5))(ids)
  kz, kmask, kar, kaf, kag = (keys[:, j] for j in range(5))
  z = jax.vmap(lambda k: jax.random.normal(k, (setup.settings.latent_dim,)))(kz)

  # Generator forward once; its VJP serves the G update.
  def fakes(p):
    out = fake_scans(setup, p, z, kmask, detached_head=setup.drops.rate_head_only)
    return ((out['scan'], out['mask']) + ((out['head_keep'],) if 'head_keep' in out else ())
            + ((out['inv_depth'],) if setup.drops.far_weight > 0 else ()))
  real, real_keep = batch, (batch > codec.ALPHA).astype(batch.dtype)
  if setup.drops.d_sees_mask or setup.drops.g_needs_mask:
    # The mask is an output G is differentiated through, not only aux.
    fake, fake_vjp = jax.vjp(fakes, _local(state.g_params, axis_name))
    mask = fake[1]
    real = (batch, real_keep)
  else:
    fake, fake_vjp, mask = jax.vjp(fakes, _local(state.g_params, axis_name),
                                   has_aux=True)

  d_params, d_opt, d_metrics = d_step(
      setup, state.d_params, state.d_opt, real, fake[:2] if isinstance(fake, tuple) else fake,
      (kar, kaf),
      (state.step % setup.r1_every) == 0, axis_name)
  g_params, g_opt, loss_g = g_step(setup, state.g_params, state.g_opt, d_params,
                                   fake, fake_vjp, kag, axis_name, real)
  fake = fake[0] if isinstance(fake, tuple) else fake
  ema = ema_update(state.ema_params, g_params, ema_decay(setup, state.step))
  metrics = dict(d_metrics, loss_g=loss_g,
                 drop_rate=jnp.mean(fake <= codec.ALPHA),
                 mask_drop_rate=jnp.mean(mask < 0.5),
                 real_drop_rate=jnp.mean(batch <= codec.ALPHA),
                 # How far the scene's range has moved: drops.depth_weight.
                 depth_gap=jnp.mean(jnp.abs(ring_depth_gap(fake, batch, axis_name))),
                 # Share of the generated returns that dip: drops.dip_weight.
                 dip_share=_dip_share(fake, axis_name),
                 real_dip_share=_dip_share(batch, axis_name),
                 # Share of them in front of both neighbours: drops.peak_weight.
                 peak_share=_share(peaks, fake, axis_name),
                 real_peak_share=_share(peaks, batch, axis_name),
                 # Share of the pixels that are returns beyond FAR_M: drops.far_weight.
                 far_share=far_share(fake, setup.sensor, axis_name),
                 real_far_share=far_share(batch, setup.sensor, axis_name))
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
  hold ``params.variables`` and whose D and optimisers are fresh."""
  setup = make_setup(config, params.sensor)
  state = init_state(setup, jax.random.key(config.seed))
  state = state.replace(g_params=params.variables, ema_params=params.variables)
  configs.save(workdir, config)
  generator.save_spec(workdir, params.sensor, setup.settings, params.angles,
                      params.tolerance)
  mngr = checkpoint.manager(workdir, keep=config.keep_checkpoints)
  checkpoint.save(mngr, 0, state, force=True)
  mngr.wait_until_finished()


def _check_finite(records, last_checkpoint):
  """``last_checkpoint``: the newest saved step (None: none yet), all of
  whose metrics were finite."""
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
  tiles = [
      [writers.inv_depth_tile(x) for x in out['scan']],
      [writers.inv_depth_tile(x) for x in out['inv_depth']],
      [writers.prob_tile(p) for p in out['measurability']],
  ]
  # One column of (x, x_tilde, measurability) per sample, stacked down.
  rows = [[t] for triple in zip(*tiles) for t in triple]
  writers.save_grid(path, rows, scale=2)


def _check_resumable(workdir: str, config):
  """Refuses, before anything is written, to resume a run whose checkpoints
  were made by another architecture."""
  if not os.path.isfile(os.path.join(workdir, configs.FILE)):
    return
  diff = configs.architecture_diff(configs.load(workdir), config)
  if diff:
    fields = '; '.join(f'{k}: run has {a!r}, config has {b!r}' for k, (a, b) in diff.items())
    raise configs.ConfigError(
        f'{workdir} holds a run of another architecture ({fields}); its checkpoints '
        'cannot be resumed with this config. Use another --workdir, or the '
        "run's own values.")


def train_and_evaluate(config, workdir: str, log=print) -> TrainState:
  """Trains from scratch or resumes from the latest checkpoint in ``workdir``."""
  configs.validate(config)
  _check_resumable(workdir, config)
  sensor = sensor_lib.from_config(config.sensor)
  mesh = parallel.data_mesh()
  parallel.local_batch_size(config.batch_size, mesh)  # checks divisibility
  is_main = jax.process_index() == 0
  setup = make_setup(config, sensor)

  data_dir = pipeline.dataset_dir(config, sensor, log=log)
  depth = arrays.load_split(data_dir, 'train', sensor)
  angles = arrays.load_angles(data_dir, sensor)
  batches = pipeline.Batches(depth, sensor, config.batch_size, config.seed,
                             jax.process_index(), jax.process_count())

  if is_main:
    configs.save(workdir, config)
    # What a trained generator is, saved before any checkpoint: loading it
    # later needs neither this trainer nor the dataset (generator.py).
    tolerance = config.tolerance
    if os.path.isfile(os.path.join(workdir, generator.SPEC_FILE)):
      tolerance = generator.read_spec(workdir)[2]  # may have been tuned since.
    generator.save_spec(workdir, sensor, setup.settings, angles, tolerance)
  mngr = checkpoint.manager(workdir, keep=config.keep_checkpoints,
                            keep_every=config.keep_every)
  root = jax.random.key(config.seed)
  k_init, k_step, k_img = jax.random.split(root, 3)
  state = init_state(setup, k_init, ring_keep_rate(depth, sensor)
                     if setup.settings.ring_bias else None)
  state, restored = checkpoint.restore_latest(mngr, state, log=log, set_aside=True)
  start = 0 if restored is None else int(restored)
  if restored is not None:
    log(f'resumed from step {start} in {workdir}')
  state = parallel.replicate(state, mesh)
  step = parallel.data_parallel(step_fn(setup), mesh)
  writer = writers.MetricWriter(workdir, enabled=is_main, resume_step=start)
  z_img = jax.random.normal(k_img, (config.num_images, setup.settings.latent_dim))

  pending = []  # (step, device metrics) not yet fetched.
  last_log = (time.time(), start)
  bar = tqdm.tqdm(total=config.num_steps, initial=start, disable=not is_main,
                  unit='step', dynamic_ncols=True, file=sys.stderr)
  done = start
  finished = False  # No error on its way: closing the writer may raise.
  try:
    for i in range(start, config.num_steps):
      batch = parallel.shard_batch(batches(i), mesh)
      state, metrics = step(state, batch, k_step)
      pending.append((i + 1, metrics))
      done = i + 1
      log_now = done % config.log_every == 0 or done == config.num_steps
      ckpt_now = done % config.checkpoint_every == 0 or done == config.num_steps
      if log_now or ckpt_now:
        records = [(s, {k: float(v) for k, v in parallel.to_host(m).items()})
                   for s, m in pending]
        pending = []
        _check_finite(records, mngr.latest_step())
        now = time.time()
        rate = (done - last_log[1]) * config.batch_size / max(now - last_log[0], 1e-9)
        last_log = (now, done)
        mean = {k: float(np.mean([m[k] for _, m in records])) for k in records[-1][1]}
        mean['images_per_sec'] = rate
        writer.write(done, mean)
        bar.set_postfix(img_s=f'{rate:.1f}', d=f'{mean["loss_d"]:.3f}',
                        g=f'{mean["loss_g"]:.3f}', drop=f'{mean["drop_rate"]:.2f}')
      if ckpt_now:
        checkpoint.save(mngr, done, state)
      if is_main and (done % config.image_every == 0 or done == config.num_steps):
        ema = generator_params(setup, state.ema_params, angles)
        _save_images(os.path.join(workdir, 'images', f'step_{done:07d}.png'),
                     ema, z_img, jax.random.key(0))
      bar.update()
    finished = True
  except KeyboardInterrupt:
    bar.close()
    checkpoint.wait(mngr)
    last = mngr.latest_step()
    raise errors.Interrupted(
        f'interrupted at step {done}; ' +
        (f'the last checkpoint is step {last}; rerun the same command to resume'
         if last is not None else
         'no checkpoint was saved yet; rerun the same command to start afresh')) from None
  finally:
    bar.close()
    try:
      checkpoint.wait(mngr)
    except BaseException:
      finished = False
      raise
    finally:
      # A second failure (the disk that failed a checkpoint also fails the
      # metrics) must not replace the one already on its way.
      writer.close(quiet=not finished)
  return state
