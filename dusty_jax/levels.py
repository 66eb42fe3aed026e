"""Drop levels per (ring, depth) cell, fitted to a trained generator.

A DUSty generator's measurability says which pixels drop; how many drop in
each part of a scan is its level. A LiDAR's keep rate depends on the laser
(the ring) and on the range of what it sees, so a cell here is a pixel's
(ring, depth bin), the bin judged from the mean (normalised inverse) depth
of the pixel's returned neighbours, itself left out
(:func:`neighbour_depth_bin`): a drop and a return are binned alike, so real
scans, whose dropped depth is unknown, and generated ones are binned the
same way.

:func:`calibrate` fits, after training, one logit offset per cell to the
generator's measurability, so that on GAN inversions of training scans each
cell keeps the share of pixels those scans keep there (its x_tilde deciding
the cells, as when a measurability is scored against held-out scans). The
measurability still ranks the pixels within a cell. The offsets are the
generator's ``depth_levels`` variable (models.ModelSettings.depth_levels); a
run directory keeps them in :data:`FILE` (generator.load applies them).
benchmarks/research/drops/README.md ("Placement: drop levels per (ring,
depth) cell"; "Levels fitted to inversions, not to samples") measures what
they change.
"""

from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np

from dusty_jax import codec, errors, files
from dusty_jax.sensor import SensorSpec

EDGES = (5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 60.0)  # metres between depth bins
BINS = len(EDGES) + 2  # bin 0 (no returned neighbour), then nearer than EDGES[0], ...
NEIGHBOURS = (1, 2)  # half-height, half-width of the neighbourhood window
PSEUDO_COUNT = 20.0  # pixels of its ring's rate that a cell's real rate starts from
MIN_PIXELS = 50  # generated returns a cell needs to get an offset of its own
FILE = 'depth_levels.npz'


def neighbour_depth_bin(scan, keep, sensor: SensorSpec, edges=EDGES):
  """(B, H, W) int: each pixel's depth bin, judged from its neighbours.

  The mean normalised inverse depth of the returned pixels (``keep``) in a
  (3, 5) window around each pixel, the pixel itself left out (columns wrap
  around, rows do not), binned by the metric ``edges``: bin 0 when no
  neighbour returned, then 1 (nearer than edges[0]) to len(edges) + 1
  (beyond edges[-1]).
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


def cells(scan, keep, sensor: SensorSpec):
  """(B, H, W) int: each pixel's cell, ring * BINS + neighbour_depth_bin;
  cells run over [0, H * BINS)."""
  bins = neighbour_depth_bin(scan, keep, sensor)
  return jnp.arange(scan.shape[1])[None, :, None] * BINS + bins


def of_x_tilde(x_tilde, sensor: SensorSpec):
  """The cells of a generated complete inverse depth (its pixels beyond
  ALPHA count as returns); not differentiated."""
  x = jax.lax.stop_gradient(x_tilde)
  return cells(x, x > codec.ALPHA, sensor)


def observed_keep(index, keep, h: int):
  """(table (H, BINS), ring (H,)): the share of pixels that returned a point
  (``keep``) in each cell (``index``, as :func:`cells` gives) and in each
  ring of scans with ``h`` rings, each cell's rate pulled towards its ring's
  by PSEUDO_COUNT pixels (a cell few pixels fall in gets about its ring's)."""
  index = np.asarray(index).ravel()
  keep = np.asarray(keep, np.float64).ravel()
  kept = np.bincount(index, keep, minlength=h * BINS)
  seen = np.bincount(index, minlength=h * BINS)
  ring = kept.reshape(h, BINS).sum(1) / np.maximum(seen.reshape(h, BINS).sum(1), 1)
  table = (kept + PSEUDO_COUNT * np.repeat(ring, BINS)) / (seen + PSEUDO_COUNT)
  return table.reshape(h, BINS), ring


def _bisect(keep, target, iterations: int):
  """Offsets o (one per entry of ``target``) with keep(o) = target, for a
  ``keep`` that rises with each offset."""
  target = np.clip(np.asarray(target, np.float64), 1e-4, 1 - 1e-4)
  lo, hi = np.full(target.shape, -30.0), np.full(target.shape, 30.0)
  for _ in range(iterations):
    mid = (lo + hi) / 2
    low = np.asarray(keep(jnp.asarray(mid, jnp.float32))) < target
    lo, hi = np.where(low, mid, lo), np.where(low, hi, mid)
  return (lo + hi) / 2


def calibrate(params, depth, latents, iterations: int = 40, batch: int = 64):
  """``params`` (a generator.GeneratorParams with a measurability) with drop
  levels fitted to the metric depth scans ``depth`` (N, H, W; the training
  split; 0 where dropped, as is NaN) and ``latents`` (N, d), their GAN
  inversions (evaluation.fit_levels makes both). Non-finite latents, and
  scans of which none returns a point, are refused (errors.InputError).

  Each scan's cells are those of its inversion's x_tilde, as in scoring a
  measurability against held-out scans. Each cell's offset is set by
  bisection so that the mean expected keep of its pixels (measurability
  times x_tilde beyond ALPHA) equals the share of them that returned a
  point (:func:`observed_keep`); a cell with fewer than MIN_PIXELS returns
  of x_tilde takes its ring's mean offset. The levels replace any
  ``params`` had: fitting again gives the same. They move no x_tilde, and
  the inversion's loss ignores the measurability, so one pass suffices.
  benchmarks/research/drops/README.md ("Levels fitted to inversions, not to
  samples") measures this fit against one to samples.
  """
  variant = params.variant
  if not variant.has_measurability:
    raise ValueError(f'calibrate: the {params.model} model has no measurability to level')
  depth = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
  latents = np.asarray(latents, np.float32)
  h = params.sensor.shape[0]
  if depth.ndim != 3 or depth.shape[1:] != tuple(params.sensor.shape):
    raise ValueError(f'calibrate: scans of shape {depth.shape}; the generator makes '
                     f'(N, {h}, {params.sensor.shape[1]})')
  if not len(depth):
    raise ValueError('calibrate: no scans to fit drop levels to')
  if latents.shape != (len(depth), params.latent_dim):
    raise ValueError(f'calibrate: latents of shape {latents.shape} for {len(depth)} scans; '
                     f'want ({len(depth)}, {params.latent_dim})')
  errors.check_finite(latents, 'calibrate: latents')
  if not np.asarray(codec.valid_depth(depth, params.sensor)).any():
    raise errors.InputError(
        f'calibrate: none of the {len(depth)} scans has a return inside the sensor\'s '
        f'range ({params.sensor.min_depth:g}-{params.sensor.max_depth:g} m; all 0, NaN '
        'or out of range): no keep rate to fit levels to')
  bare = without_levels(params)
  apply = jax.jit(bare.module().apply)
  raw = jnp.concatenate([apply(bare.variables, latents[i:i + batch])
                         for i in range(0, len(latents), batch)])
  x = variant.decode_inv_depth(raw)
  index = of_x_tilde(x, params.sensor)
  flat = np.asarray(index).ravel()
  target, _ = observed_keep(flat, codec.valid_depth(depth, params.sensor), h)
  count = np.bincount(flat, minlength=h * BINS)
  returns = np.bincount(flat, np.asarray(x > codec.ALPHA).ravel(), minlength=h * BINS)

  def per_cell(offset):  # the mean expected keep of each cell with the offsets
    moved = raw.at[..., 1].add(offset[index])
    keep = variant.measurability(variant.logit(moved)) * (x > codec.ALPHA)
    return jax.ops.segment_sum(keep.ravel(), index.ravel(), h * BINS) / jnp.maximum(count, 1)
  offset = _bisect(jax.jit(per_cell), target.ravel(), iterations).reshape(h, BINS)
  fitted = (returns >= MIN_PIXELS).reshape(h, BINS)
  weight = np.where(fitted, returns.reshape(h, BINS), 0)
  mean = (offset * weight).sum(1) / np.maximum(weight.sum(1), 1)
  return with_levels(bare, np.where(fitted, offset, mean[:, None]))


def without_levels(params):
  """``params`` without drop levels (the generator as trained)."""
  if not params.settings.depth_levels:
    return params
  p = {k: v for k, v in params.variables['params'].items() if k != 'depth_levels'}
  settings = dataclasses.replace(params.settings, depth_levels=False)
  return params.replace(variables={**params.variables, 'params': p}, settings=settings)


def with_levels(params, offset, source: str = 'depth levels'):
  """``params`` whose ``depth_levels`` are theirs plus ``offset`` (H, BINS);
  ``source`` names the offsets in the error for another shape."""
  want = (params.sensor.shape[0], BINS)
  if np.shape(offset) != want:
    raise ValueError(f'{source}: levels of shape {np.shape(offset)}; this generator\'s are {want}')
  p = dict(params.variables['params'])
  old = np.asarray(p.get('depth_levels', 0.0), np.float64)
  p['depth_levels'] = jnp.asarray(old + np.asarray(offset, np.float64), jnp.float32)
  settings = dataclasses.replace(params.settings, depth_levels=True)
  return params.replace(variables={**params.variables, 'params': p}, settings=settings)


def save(workdir: str, levels, step: int):
  """Writes a run's fitted levels (H, BINS) and the step they fit (atomically)."""
  path = os.path.join(workdir, FILE)
  with files.atomic_write(path, 'wb') as f:
    np.savez(f, levels=np.asarray(levels, np.float32), step=np.int64(step))


def load(workdir: str):
  """(levels, step) a run keeps in FILE, or None where it has none."""
  path = os.path.join(workdir, FILE)
  if not os.path.isfile(path):
    return None
  try:
    with np.load(path, allow_pickle=False) as f:
      return np.asarray(f['levels'], np.float32), int(f['step'])
  except (OSError, ValueError, KeyError) as e:
    raise ValueError(f'{path}: not a file of drop levels ({e}); delete it and fit them '
                     'again (dusty_jax.evaluation.fit_levels)') from None
