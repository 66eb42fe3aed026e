"""Chamfer distance and pairwise Chamfer matrices between sets of clouds.

CD(a, b) = mean_i min_j |a_i - b_j|^2 + mean_j min_i |a_i - b_j|^2 (squared
distances, no square root), as PointFlow's evaluation. Matrices are computed
in tiles of clouds, so nothing of size (n, m, P, P) or (n, m, 3) is ever
materialised; within a tile each pair's P x P distances are formed once and
reduced along both axes. A set against itself computes each unordered pair
once.

The tile kernel loops over the points of one side, keeping a running
minimum over the other side's points for every pair of the tile, and takes
UNROLL points per iteration so the accumulator is read and written once per
UNROLL points. Distances are expanded as |x|^2 - 2 x.y (+ |y|^2 after the
minimum), three multiply-adds per point pair; rounding leaves errors of
about 1e-7 |x|^2 (so a cloud against itself gives about 1e-9, not exactly 0,
in units of 120 m). Measured on the 2-core CPU: see benchmarks/chamfer_fps.py.
"""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
import tqdm

from dusty_jax import errors


@jax.jit
def chamfer(a, b):
  """CD between two clouds (P, 3) and (Q, 3), by explicit differences."""
  d = jnp.sum(jnp.square(a[:, None, :] - b[None, :, :]), -1)
  return d.min(axis=1).mean() + d.min(axis=0).mean()


UNROLL = 8


def _pad_points(x, multiple):
  """Pads clouds (n, P, 3) to a multiple of points with their first point."""
  extra = (-x.shape[1]) % multiple
  if not extra:
    return x
  return jnp.concatenate([x, jnp.repeat(x[:, :1], extra, axis=1)], axis=1)


def _nearest_means(x, y):
  """(n, P, 3), (m, Q, 3) -> (n, m): mean over y's points of the squared
  distance to the nearest point of x."""
  x = _pad_points(x, UNROLL)
  n, p = x.shape[:2]
  y2m = -2.0 * jnp.moveaxis(y, -1, 0)  # (3, m, Q)
  x2 = jnp.sum(x * x, -1).reshape(n, p // UNROLL, UNROLL)
  xs = x.reshape(n, p // UNROLL, UNROLL, 3)

  def body(i, acc):
    xi, x2i = xs[:, i], x2[:, i]
    for u in range(UNROLL):
      c = xi[:, u, :, None, None]  # (n, 3, 1, 1)
      d = (x2i[:, u, None, None] + c[:, 0] * y2m[0][None] + c[:, 1] * y2m[1][None]
           + c[:, 2] * y2m[2][None])
      acc = jnp.minimum(acc, d)
    return acc

  acc = jnp.full((n,) + y.shape[:2], jnp.inf, x.dtype)
  acc = jax.lax.fori_loop(0, p // UNROLL, body, acc)
  return jnp.maximum(acc + jnp.sum(y * y, -1)[None], 0.0).mean(-1)


@jax.jit
def _tile(a, b):
  """(ta, P, 3) x (tb, Q, 3) -> (ta, tb) Chamfer distances."""
  return _nearest_means(b, a).T + _nearest_means(a, b)


def pairwise(a, b=None, tile: int = 8, progress: bool = False):
  """(n, m) Chamfer matrix between sets a (n, P, 3) and b (m, Q, 3).

  With ``b`` None, the symmetric matrix of ``a`` against itself, with each
  off-diagonal tile computed once and mirrored.
  """
  a = np.asarray(errors.check_finite(a, 'clouds a'), np.float32)
  sym = b is None
  b = a if sym else np.asarray(errors.check_finite(b, 'clouds b'), np.float32)
  n, m = len(a), len(b)
  out = np.zeros((n, m), np.float32)
  starts_a = range(0, n, tile)
  jobs = [(i, j) for i in starts_a for j in range(0, m, tile) if not sym or j >= i]
  pad = lambda x, s: np.concatenate([x, np.repeat(x[-1:], s - len(x), 0)]) if len(x) < s else x
  for i, j in tqdm.tqdm(jobs, disable=not progress, desc='chamfer', unit='tile'):
    ta, tb = a[i:i + tile], b[j:j + tile]
    block = np.asarray(_tile(pad(ta, tile), pad(tb, tile)))[:len(ta), :len(tb)]
    out[i:i + len(ta), j:j + len(tb)] = block
    if sym and j > i:
      out[j:j + len(tb), i:i + len(ta)] = block.T
  return out
