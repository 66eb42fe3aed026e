"""Point-drop mechanisms beyond the paper (config ``drops``).

All are off by default, which trains as the authors do. The trainer calls
this module through four hooks:
  * :func:`init_biases`: where the measurability starts (``mask_bias``,
    ``ring_bias``);
  * :func:`add_penalties`: the terms added to G's loss;
  * :attr:`DropOptions.g_needs_mask`: whether G's loss differentiates the
    keep-mask itself (not only the scan);
  * :func:`diagnostics`: the drop metrics a train step logs.
The terms and setters are pure functions, each tested alone
(tests/test_drops.py). With ``axis_name`` every tally is the global batch's
(summed over the devices), so N devices compute what one does.

experiments/study.py's ``PRESETS`` name the options the shipped models
trained with; the rest of the screened combinations are in
benchmarks/research/drops/lineage.py.
"""

from __future__ import annotations

import dataclasses

import flax
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from dusty_jax import codec, levels
from dusty_jax.metrics import ground_truth
from dusty_jax.sensor import SensorSpec


@dataclasses.dataclass(frozen=True)
class DropOptions:
  """The options of config ``drops`` that act on training (configs.drop_defaults
  is made of these fields and their defaults, all off, and ``ring_bias``,
  which changes the networks: models.ModelSettings owns it).

  Attributes:
    mask_bias: the measurability logit's initial bias (the authors' is 0:
      half the pixels dropped at the start); logit(keep rate) starts there.
    rate_weight: lambda: G's loss + lambda * the squared gap between the
      generated and the real batch's keep rate of each (ring, neighbours'
      depth bin) cell (:func:`ring_depth_rate_penalty`): drops that depend
      on the range within a ring, as a sensor's do. (The rate of the whole
      batch and of each ring lost to it: benchmarks/research/drops/.)
    rate_head_only: the rate term is taken on the expected keep
      (the measurability, not the sampled mask) of the head applied to the
      trunk's features under stop_gradient, so it trains the measurability
      head and its biases and leaves G's shared trunk to the GAN loss.
    mask_detached: the measurability comes from the head on the trunk's
      features under stop_gradient (the same values), so no gradient of the
      mask (the GAN's straight-through one included) reaches the trunk: it
      learns from x_tilde alone, the head's measurability part from the mask.
    dip_weight: nu: G's loss + nu * the mean depth of the dips among the
      generated returns (:func:`dip_penalty`): a checkerboard of far pixels
      that looks like drops to D, which real surfaces hardly have.
    depth_levels: after training, the EMA generator's drop level is fitted
      per (ring, depth) cell to inversions of the training split's first
      256 scans (evaluation.fit_levels) and kept in the run (levels.FILE),
      which loading it applies. Training itself is unchanged.
  """
  mask_bias: float = 0.0
  rate_weight: float = 0.0
  rate_head_only: bool = False
  mask_detached: bool = False
  dip_weight: float = 0.0
  depth_levels: bool = False

  @classmethod
  def from_config(cls, drops) -> 'DropOptions':
    """``drops``: a config's validated ``drops`` group (configs.validate)."""
    return cls(**{f.name: type(f.default)(drops[f.name]) for f in dataclasses.fields(cls)})

  @property
  def g_needs_mask(self) -> bool:
    """G's loss differentiates the keep-mask itself (not only the scan)."""
    return self.rate_weight > 0


def _psum(x, axis_name):
  return x if axis_name is None else lax.psum(x, axis_name)


# ----------------------------------------------------------------------------
# Where the measurability starts.
# ----------------------------------------------------------------------------


def set_mask_bias(g_params, bias: float):
  """G's variables with the pixel measurability logit's bias set to ``bias``
  (head channel 1; DUSty-II's image-level logit is left alone)."""
  p = flax.core.unfreeze(g_params) if hasattr(g_params, 'unfreeze') else g_params
  head_bias = p['params']['head_bias'].at[1].set(bias)
  return {**p, 'params': {**p['params'], 'head_bias': head_bias}}


RING_KEEP_CLIP = 0.01  # keep rates start within [0.01, 0.99]: finite logits.


def ring_keep_rate(depth, sensor: SensorSpec, num: int = 1024) -> np.ndarray:
  """(H,) the fraction of returned pixels per ring over the first ``num``
  scans of ``depth`` (metric, 0 or out of range: dropped)."""
  return ground_truth.ring_keep_rate(depth[:num], sensor)


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


def init_biases(options: DropOptions, g_params, ring_keep=None):
  """Fresh G variables with the measurability's starting biases: the global
  ``mask_bias``, and with ``ring_keep`` ((H,) the training data's keep rate
  per ring, given where the network has a ring bias:
  models.ModelSettings.ring_bias) one offset per ring from it (without it
  the offsets stay 0)."""
  if options.mask_bias:
    g_params = set_mask_bias(g_params, options.mask_bias)
  if ring_keep is not None:
    g_params = set_ring_bias(g_params, ring_keep, options.mask_bias)
  return g_params


# ----------------------------------------------------------------------------
# The terms of G's loss.
# ----------------------------------------------------------------------------


def add_penalties(options: DropOptions, sensor: SensorSpec, loss, fake, real,
                  axis_name=None):
  """G's ``loss`` plus the terms of the options that are on, each times its
  weight. ``fake``: the generated scans (trainer.Fake: ``scan``, and where
  :attr:`DropOptions.g_needs_mask` their keep-mask ``mask``, with
  ``rate_head_only`` the detached head's ``head_keep``); ``real``: the real batch's
  (scans, keep-masks), or None where no option is on."""
  if options.dip_weight > 0:
    loss = loss + options.dip_weight * dip_penalty(fake.scan, axis_name)
  keep = fake.head_keep if options.rate_head_only else fake.mask  # what the term moves
  if options.rate_weight > 0:
    loss = loss + options.rate_weight * ring_depth_rate_penalty(
        sensor, (fake.scan, fake.mask), real, axis_name, keep)
  return loss




DIP = 0.05  # normalised inverse depth: how far behind both ring neighbours a dip lies


def dips(scan, dip: float = DIP):
  """(depths, counted): per pixel of ``scan`` (B, H, W), how far it lies
  behind both ring neighbours beyond ``dip`` (0 if not), and whether it and
  both neighbours are returns (> ALPHA; the ring wraps around). The
  neighbours and the masks are not differentiated."""
  keep = lax.stop_gradient(scan > codec.ALPHA)
  left, right = jnp.roll(scan, 1, -1), jnp.roll(scan, -1, -1)
  bound = lax.stop_gradient(jnp.minimum(left, right))
  counted = keep & jnp.roll(keep, 1, -1) & jnp.roll(keep, -1, -1)
  return jnp.where(counted, jax.nn.relu(bound - scan - dip), 0.0), counted


def dip_share(scan, axis_name=None):
  """The share of the counted pixels of ``scan`` that dip (:func:`dips`)."""
  amount, counted = dips(scan)
  return _psum((amount > 0).sum(), axis_name) / jnp.maximum(_psum(counted.sum(), axis_name), 1)


def dip_penalty(scan, axis_name=None):
  """``dip_weight``'s term: the mean dip depth over the counted pixels."""
  amount, counted = dips(scan)
  return _psum(amount.sum(), axis_name) / jnp.maximum(_psum(counted.sum(), axis_name), 1)


# The rate term's cells are levels.py's (ring, neighbours' depth bin).
RATE_DEPTH_EDGES, RATE_DEPTH_BINS = levels.EDGES, levels.BINS
neighbour_depth_bin, ring_depth_cells = levels.neighbour_depth_bin, levels.cells


def cell_rate_penalty(keep, real_keep, cells, real_cells, num_cells: int, axis_name=None):
  """The squared gap between the generated and the real keep rate of each
  cell of ``cells`` / ``real_cells`` (ints in [0, num_cells): one per
  pixel), weighted by the generated pixels in the cell, so each generated
  pixel is pulled towards its cell's real rate as the other rate terms pull
  it towards the ring's. Cells empty on either side weigh 0.
  """
  flat = lambda a: a.reshape(-1)
  count = lambda c, w: _psum(jax.ops.segment_sum(flat(w), flat(c), num_cells), axis_name)
  ones = jnp.ones_like(keep)
  n_fake, n_real = count(cells, ones), count(real_cells, ones)
  fake_rate = count(cells, keep) / jnp.maximum(n_fake, 1.0)
  kept_real = lax.stop_gradient(count(real_cells, real_keep))
  real_rate = kept_real / jnp.maximum(n_real, 1.0)
  weight = jnp.where(n_real > 0, n_fake, 0.0)
  return jnp.sum(weight * jnp.square(fake_rate - real_rate)) / jnp.maximum(weight.sum(), 1.0)


def ring_depth_rate_penalty(sensor: SensorSpec, fake, real, axis_name=None, keep=None):
  """``rate_weight``'s term: the cell rate penalty over (ring, depth bin)
  cells. ``fake`` and ``real``: (scans, keep-masks) pairs; the cells are not
  differentiated. ``keep``: the generated keep values to differentiate
  (default: the mask ``fake[1]``, which bins the cells)."""
  cells = lambda scan, keep: ring_depth_cells(lax.stop_gradient(scan),
                                              lax.stop_gradient(keep) > 0.5, sensor)
  h = fake[0].shape[1]
  keep = fake[1] if keep is None else keep
  return cell_rate_penalty(keep, real[1], cells(*fake), cells(*real), h * RATE_DEPTH_BINS,
                           axis_name)


# ----------------------------------------------------------------------------
# What a train step logs.
# ----------------------------------------------------------------------------


def diagnostics(scan, mask, real, axis_name=None) -> dict:
  """The drop metrics of one step: of the generated ``scan`` (B, H, W) with
  its keep-``mask``, and of the ``real`` scans (drops at or below ALPHA)."""
  return dict(
      drop_rate=jnp.mean(scan <= codec.ALPHA),
      mask_drop_rate=jnp.mean(mask < 0.5),
      real_drop_rate=jnp.mean(real <= codec.ALPHA),
      # Share of the generated returns that dip: dip_weight.
      dip_share=dip_share(scan, axis_name),
      real_dip_share=dip_share(real, axis_name))
