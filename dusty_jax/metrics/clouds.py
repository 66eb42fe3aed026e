"""Point clouds for evaluation: back-projection and farthest point sampling.

Clouds are in units of the sensor's max range (120 m), as the reference
metric code expects; dropped pixels are excluded.

Farthest point sampling starts from the first valid pixel in raster order
(row-major over the range image, i.e. the top ring's first column).
Dropped pixels are never selected. The DUSty authors' CUDA kernel differs:
it always starts at pixel 0 (a dropped pixel in most scans, so their clouds
contain the origin) and never picks points within sqrt(1e-3) x 120 m =
3.79 m of the sensor; the two agree only when pixel 0 is valid and no valid
point is that near. A cloud with fewer valid points than
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


FPS_CHUNK = 64   # clouds sampled together (vectorised across clouds).
FPS_UNROLL = 4


@functools.partial(jax.jit, static_argnames='k')
def _fps_chunk(points, valid, k: int):
  """(B, N, 3), (B, N) -> (B, k): clouds on the minor axis, so every step's
  update and both reductions vectorise across clouds. Ties go to the lowest
  index (the first maximum)."""
  b, n = valid.shape
  x, y, z = (points[..., c].T for c in range(3))  # (N, B) each
  v = valid.T
  iota = jnp.arange(n, dtype=jnp.int32)[:, None]
  cols = jnp.arange(b)
  start = jnp.min(jnp.where(v, iota, n), axis=0).astype(jnp.int32)
  start = jnp.minimum(start, n - 1)
  dist = jnp.where(v, jnp.inf, -jnp.inf).at[start, cols].set(0.0)

  def body(i, carry):
    idx, dist, last = carry
    d = (jnp.square(x - x[last, cols]) + jnp.square(y - y[last, cols])
         + jnp.square(z - z[last, cols]))
    dist = jnp.minimum(dist, d)
    top = jnp.max(dist, axis=0)
    nxt = jnp.min(jnp.where(dist == top, iota, n), axis=0).astype(jnp.int32)
    return idx.at[i].set(nxt), dist, nxt

  idx = jnp.zeros((k, b), jnp.int32).at[0].set(start)
  idx, _, _ = jax.lax.fori_loop(1, k, body, (idx, dist, start), unroll=FPS_UNROLL)
  return idx.T


def farthest_point_indices(points, valid, k: int, chunk: int = FPS_CHUNK):
  """(B, N, 3), (B, N) -> (B, k) indices of farthest point samples."""
  points = np.asarray(points, np.float32)
  valid = np.asarray(valid, bool)
  out = []
  for i in range(0, len(points), chunk):
    p, v = points[i:i + chunk], valid[i:i + chunk]
    m = len(p)
    if m < chunk and len(points) > chunk:  # keep one compiled shape
      p = np.concatenate([p, np.repeat(p[-1:], chunk - m, 0)])
      v = np.concatenate([v, np.repeat(v[-1:], chunk - m, 0)])
    out.append(np.asarray(_fps_chunk(p, v, k))[:m])
  return np.concatenate(out) if out else np.zeros((0, k), np.int32)


def farthest_point_sample(points, valid, k: int):
  """(B, N, 3) clouds with (B, N) validity -> (B, k, 3) subsampled clouds."""
  points, valid = jnp.asarray(points), jnp.asarray(valid, bool)
  empty = np.flatnonzero(~np.asarray(valid.any(axis=1)))
  if empty.size:
    raise ValueError(f'clouds {empty[:10].tolist()} have no valid point to '
                     'sample (every pixel dropped)')
  idx = farthest_point_indices(points, valid, k)
  return jnp.take_along_axis(points, jnp.asarray(idx)[..., None], axis=1)
