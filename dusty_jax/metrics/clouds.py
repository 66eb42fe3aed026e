"""Point clouds for evaluation: back-projection and farthest point sampling.

Clouds are in units of the sensor's max range (120 m), as the reference
metric code expects; dropped pixels are excluded.

Farthest point sampling, ``protocol='reference'`` (the default): the first
sample is the first valid pixel in raster order (row-major over the range
image, i.e. the top ring's first column), and dropped pixels are never
selected; ties go to the lowest index. A cloud with fewer valid points than
asked for repeats its points (after every valid point is taken, the
farthest remaining distance is 0 and the first valid point is chosen
again); a cloud with no valid point cannot be sampled and raises.

``protocol='paper'`` computes what the DUSty authors' CUDA kernel (from
Pointnet2_PyTorch) computes on their clouds, where dropped pixels sit at the
origin: the first sample is always pixel 0, valid or not (a dropped pixel in
most scans, so their clouds contain the origin); afterwards only points
with a squared norm above PAPER_MIN_SQUARED_NORM (units of max_depth:
farther than sqrt(1e-3) x 120 m = 3.79 m) can be picked, dropped pixels
among the excluded. Ties (equal distances, e.g. duplicate points) are
broken as the kernel's thread layout and block reduction break them (see
paper_tie_order). A cloud with no point beyond 3.79 m repeats pixel 0, as
the kernel does, instead of raising. The two protocols agree only when
pixel 0 is valid and no valid point is that near.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from dusty_jax import codec, errors
from dusty_jax.sensor import SensorSpec


def scans_to_clouds(scans, angles, sensor: SensorSpec, tolerance: float = 0.0):
  """(B, H, W) inverse-depth scans -> (B, H*W, 3) points / max_depth, valid."""
  depth, valid = codec.decode(scans, sensor, tolerance)
  pts = codec.to_points(depth, angles) / sensor.max_depth
  b = pts.shape[0]
  return pts.reshape(b, -1, 3), valid.reshape(b, -1)


FPS_CHUNK = 64   # clouds sampled together (vectorised across clouds).
FPS_UNROLL = 4

PROTOCOLS = ('reference', 'paper')
# The authors' kernel skips points with x^2 + y^2 + z^2 <= 1e-3 (units of
# max_depth), i.e. within sqrt(1e-3) * 120 m = 3.79 m of the sensor.
PAPER_MIN_SQUARED_NORM = 1e-3
PAPER_MAX_THREADS = 512  # the kernel's TOTAL_THREADS.


def check_protocol(protocol: str) -> str:
  if protocol not in PROTOCOLS:
    raise ValueError(f'unknown protocol {protocol!r}; expected one of {PROTOCOLS}')
  return protocol


def paper_threads(n: int) -> int:
  """Threads per cloud of the authors' kernel: the largest power of two not
  above n, at most 512 (their opt_n_threads; 512 for every n >= 512)."""
  return max(min(1 << (max(n, 1).bit_length() - 1), PAPER_MAX_THREADS), 1)


def paper_tie_order(n: int) -> np.ndarray:
  """Indices 0..n-1 in the order the authors' kernel prefers them on ties.

  Thread t walks indices t, t + T, ... keeping the first of equal maxima;
  the block reduction then merges slot t + s into slot t for s = T/2, ...,
  1, keeping slot t on ties. Two threads meet at the stride of their lowest
  differing bit, where the one with that bit clear wins: threads rank by
  their bit-reversed id, then indices within a thread by position.
  """
  t = paper_threads(n)
  bits = t.bit_length() - 1
  tid = np.arange(t)
  rev = np.zeros(t, np.int64)
  for b in range(bits):
    rev |= ((tid >> b) & 1) << (bits - 1 - b)
  idx = np.arange(n)
  return idx[np.lexsort((idx // t, rev[idx % t]))].astype(np.int32)


@functools.partial(jax.jit, static_argnames=('k', 'paper'))
def _fps_chunk(points, valid, k: int, paper: bool = False):
  """(B, N, 3), (B, N) -> (B, k): clouds on the minor axis, so every step's
  update and both reductions vectorise across clouds.

  ``valid`` marks the points that may be picked after the first. Reference:
  the first is the first valid point, ties go to the lowest index. Paper:
  the first is point 0, ties go to the point first in paper_tie_order.
  """
  b, n = valid.shape
  x, y, z = (points[..., c].T for c in range(3))  # (N, B) each
  v = valid.T
  cols = jnp.arange(b)
  iota = jnp.arange(n, dtype=jnp.int32)[:, None]
  if paper:
    order = paper_tie_order(n)
    rank = jnp.asarray(np.argsort(order).astype(np.int32)[:, None])
    order = jnp.asarray(order)
    to_index = lambda r: order[r]
    start = jnp.zeros((b,), jnp.int32)
    dist = jnp.where(v, jnp.inf, -jnp.inf)
  else:
    rank, to_index = iota, lambda r: r
    start = jnp.min(jnp.where(v, iota, n), axis=0).astype(jnp.int32)
    start = jnp.minimum(start, n - 1)
    dist = jnp.where(v, jnp.inf, -jnp.inf).at[start, cols].set(0.0)

  def body(i, carry):
    idx, dist, last = carry
    d = (jnp.square(x - x[last, cols]) + jnp.square(y - y[last, cols])
         + jnp.square(z - z[last, cols]))
    dist = jnp.minimum(dist, d)
    top = jnp.max(dist, axis=0)
    nxt = to_index(jnp.min(jnp.where(dist == top, rank, n), axis=0)).astype(jnp.int32)
    return idx.at[i].set(nxt), dist, nxt

  idx = jnp.zeros((k, b), jnp.int32).at[0].set(start)
  idx, _, _ = jax.lax.fori_loop(1, k, body, (idx, dist, start), unroll=FPS_UNROLL)
  return idx.T


def farthest_point_indices(points, valid, k: int, chunk: int = FPS_CHUNK,
                           protocol: str = 'reference'):
  """(B, N, 3), (B, N) -> (B, k) indices of farthest point samples.

  With ``protocol='paper'`` the points must already hold dropped pixels at
  the origin (as :func:`farthest_point_sample` arranges); ``valid`` is not
  used then, only each point's distance from the sensor.
  """
  paper = check_protocol(protocol) == 'paper'
  points = np.asarray(points, np.float32)
  if paper:
    valid = np.sum(np.square(points), -1) > np.float32(PAPER_MIN_SQUARED_NORM)
  else:
    valid = np.asarray(valid, bool)
  out = []
  for i in range(0, len(points), chunk):
    p, v = points[i:i + chunk], valid[i:i + chunk]
    m = len(p)
    if m < chunk and len(points) > chunk:  # keep one compiled shape
      p = np.concatenate([p, np.repeat(p[-1:], chunk - m, 0)])
      v = np.concatenate([v, np.repeat(v[-1:], chunk - m, 0)])
    out.append(np.asarray(_fps_chunk(p, v, k, paper))[:m])
  return np.concatenate(out) if out else np.zeros((0, k), np.int32)


def farthest_point_sample(points, valid, k: int, protocol: str = 'reference'):
  """(B, N, 3) clouds with (B, N) validity -> (B, k, 3) subsampled clouds.

  ``protocol='paper'`` first moves dropped points to the origin, where the
  authors' clouds hold them, so a sampled pixel 0 that is dropped is the
  origin.
  """
  points, valid = jnp.asarray(points), jnp.asarray(valid, bool)
  if check_protocol(protocol) == 'paper':
    points = jnp.where(valid[..., None], points, 0.0)
  else:
    empty = np.flatnonzero(~np.asarray(valid.any(axis=1)))
    if empty.size:
      raise errors.InputError(f'clouds {empty[:10].tolist()} have no valid point to '
                              'sample (every pixel dropped)')
  idx = farthest_point_indices(points, valid, k, protocol=protocol)
  return jnp.take_along_axis(points, jnp.asarray(idx)[..., None], axis=1)
