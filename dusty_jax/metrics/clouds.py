"""Point clouds for evaluation: back-projection and farthest point sampling.

Clouds are in units of the sensor's max range (120 m), as the reference
metric code expects; dropped pixels are excluded.

Farthest point sampling starts from the first valid pixel in raster order
(row-major over the range image, i.e. the top ring's first column), the
deterministic choice of the reference CUDA kernel, which starts at index 0.
Dropped pixels are never selected. A cloud with fewer valid points than
asked for repeats its points (after every valid point is taken, the farthest
remaining distance is 0 and the first valid point is chosen again); a cloud
with no valid point cannot be sampled and raises.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from dusty_jax import projection
from dusty_jax.sensor import SensorSpec


def scans_to_clouds(scans, angles, sensor: SensorSpec, tolerance: float = 0.0):
  """(B, H, W) inverse-depth scans -> (B, H*W, 3) points / max_depth, valid."""
  depth, valid = projection.decode(scans, sensor, tolerance)
  pts = projection.to_points(depth, angles) / sensor.max_depth
  b = pts.shape[0]
  return pts.reshape(b, -1, 3), valid.reshape(b, -1)


def _fps_one(points, valid, k: int):
  n = points.shape[0]
  start = jnp.argmax(valid)
  dist = jnp.where(valid, jnp.inf, -jnp.inf)

  def body(i, carry):
    idx, dist = carry
    last = points[idx[i - 1]]
    d = jnp.sum(jnp.square(points - last), axis=-1)
    dist = jnp.minimum(dist, d)
    return idx.at[i].set(jnp.argmax(dist).astype(jnp.int32)), dist

  idx = jnp.zeros((k,), jnp.int32).at[0].set(start.astype(jnp.int32))
  dist = dist.at[start].set(0.0)
  idx, _ = jax.lax.fori_loop(1, k, body, (idx, dist))
  return idx


@functools.partial(jax.jit, static_argnames='k')
def farthest_point_indices(points, valid, k: int):
  """(B, N, 3), (B, N) -> (B, k) indices of farthest point samples."""
  return jax.vmap(lambda p, v: _fps_one(p, v, k))(points, valid)


def farthest_point_sample(points, valid, k: int):
  """(B, N, 3) clouds with (B, N) validity -> (B, k, 3) subsampled clouds."""
  points, valid = jnp.asarray(points), jnp.asarray(valid, bool)
  empty = np.flatnonzero(~np.asarray(valid.any(axis=1)))
  if empty.size:
    raise ValueError(f'clouds {empty[:10].tolist()} have no valid point to '
                     'sample (every pixel dropped)')
  idx = farthest_point_indices(points, valid, k)
  return jnp.take_along_axis(points, idx[..., None], axis=1)
