"""Distribution metrics over sets of point clouds (PointFlow's definitions).

Given Chamfer matrices between reference clouds R and generated clouds S:
  * MMD: mean over reference clouds of the distance to the nearest generated
    cloud (lower is better);
  * COV: share of reference clouds that are the nearest neighbour of at
    least one generated cloud (higher is better);
  * 1-NNA: leave-one-out 1-nearest-neighbour accuracy of telling R from S
    over their union (50% is ideal, 100% means fully separable).
  * JSD: Jensen-Shannon divergence (base 2) between the occupancy of a
    28^3 grid over [-0.5, 0.5]^3 restricted to its inscribed sphere, each
    point counted at its nearest grid point, counts summed over each set
    (latent_3d_points' definition). Clouds in units of 120 m are divided by
    2 first, as the DUSty authors do.

JSD with ``protocol='paper'`` is the DUSty authors' computation: their
entropy adds eps = 1e-8 to its argument in place, so each set's normalised
counts are shifted by eps when their own entropy is taken, and the mixture,
formed afterwards from the shifted vectors, is shifted by eps once more:
  JSD_paper = H(m + 2 eps) - (H(p + eps) + H(q + eps)) / 2,  m = (p + q) / 2,
with H(v) = -sum v log2 v over every cell of the grid. A cell empty in both
sets adds -2 eps - eps log2(eps) = 2.46e-7; with about 10^4 such cells,
identical sets score about 0.0024 instead of 0.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from dusty_jax import errors


def mmd_cov(d_sr):
  """MMD and COV from the (num_generated, num_reference) Chamfer matrix."""
  d_sr = errors.check_finite(np.asarray(d_sr), 'the Chamfer matrix')
  if d_sr.size == 0:
    raise errors.InputError('MMD/COV need at least one generated and one reference '
                            f'cloud, got a matrix of shape {d_sr.shape}')
  mmd = float(d_sr.min(axis=0).mean())
  cov = float(len(np.unique(d_sr.argmin(axis=1))) / d_sr.shape[1])
  return mmd, cov


def one_nna(d_rr, d_rs, d_ss):
  """Leave-one-out 1-NN accuracy over R u S (ties: the lowest index wins).

  PointFlow's definition, degenerate sets included: identical sets (each
  cloud with an exact copy in the other set) score 0, every cloud's nearest
  neighbour being its copy, of the other label; that is the memorisation
  end, where 50% is two independent samples of one distribution. Sets of
  one repeated cloud tie everywhere: the lowest index, a reference cloud,
  is every cloud's neighbour, so R scores right and S wrong: n0 / (n0 + n1).
  The matrices must be finite (errors.InputError).
  """
  d_rr, d_rs, d_ss = (errors.check_finite(np.asarray(d), what) for d, what in
                      ((d_rr, 'd_rr'), (d_rs, 'd_rs'), (d_ss, 'd_ss')))
  n0, n1 = len(d_rr), len(d_ss)
  if n0 < 1 or n1 < 1 or n0 + n1 < 3:
    raise errors.InputError(f'1-NNA needs both sets non-empty and 3 clouds in all, got '
                            f'{n0} and {n1}')
  full = np.block([[d_rr, d_rs], [d_rs.T, d_ss]]).astype(np.float64)
  np.fill_diagonal(full, np.inf)
  label = np.concatenate([np.ones(n0), np.zeros(n1)])
  pred = label[np.argmin(full, axis=0)]
  return float(np.mean(pred == label))


# --- JSD on an occupancy grid -------------------------------------------------

JSD_RESOLUTION = 28


@functools.lru_cache(maxsize=4)
def _grid(resolution: int):
  """Sphere grid points, full-grid -> sphere index, and the boundary shell."""
  ax = np.arange(resolution) / (resolution - 1) - 0.5
  full = np.stack(np.meshgrid(ax, ax, ax, indexing='ij'), -1).reshape(-1, 3)
  inside = np.linalg.norm(full, axis=1) <= 0.5
  sphere = full[inside]
  index = np.full(len(full), -1)
  index[inside] = np.arange(len(sphere))
  # Shell: sphere points with a 6-neighbour outside the sphere (or the cube).
  cube = inside.reshape((resolution,) * 3)
  padded = np.pad(cube, 1, constant_values=False)
  interior = np.ones_like(cube)
  for axis in range(3):
    for shift in (-1, 1):
      interior &= np.roll(padded, shift, axis)[1:-1, 1:-1, 1:-1]
  shell = np.flatnonzero((cube & ~interior).ravel()[inside])
  return sphere.astype(np.float32), index, shell


@jax.jit
def _nearest_shell(points, shell_pts):
  """Index into the shell of each point's nearest shell grid point."""
  d = (jnp.sum(points * points, -1)[:, None] + jnp.sum(shell_pts * shell_pts, -1)[None]
       - 2.0 * points @ shell_pts.T)
  return jnp.argmin(d, axis=1)


SHELL_CHUNK = 4096


def occupancy(clouds, valid=None, resolution: int = JSD_RESOLUTION, scale=0.5):
  """Grid counts of a set of clouds (B, P, 3), scaled by ``scale`` first.

  Each point counts at its nearest grid point inside the sphere. The nearest
  full-grid point comes from rounding; only when that lies outside the
  sphere is the nearest sphere point searched for, and then only on the
  sphere's boundary shell (an interior point always has a closer neighbour
  towards the query).
  """
  pts = np.asarray(clouds, np.float32).reshape(-1, 3) * scale
  ok = (np.ones(len(pts), bool) if valid is None
        else np.asarray(valid, bool).reshape(-1))
  pts = pts[ok]
  sphere, index, shell = _grid(resolution)
  with np.errstate(over='ignore'):  # a point beyond 1e37 goes to inf, then the edge
    ijk = np.clip(np.rint((pts + 0.5) * (resolution - 1)), 0, resolution - 1).astype(np.int64)
  cell = index[(ijk[:, 0] * resolution + ijk[:, 1]) * resolution + ijk[:, 2]]
  outside = np.flatnonzero(cell < 0)
  shell_pts = jnp.asarray(sphere[shell])
  for i in range(0, len(outside), SHELL_CHUNK):
    sel = outside[i:i + SHELL_CHUNK]
    chunk = np.zeros((SHELL_CHUNK, 3), np.float32)  # one compiled shape
    chunk[:len(sel)] = pts[sel]
    cell[sel] = shell[np.asarray(_nearest_shell(jnp.asarray(chunk), shell_pts))[:len(sel)]]
  return np.bincount(cell, minlength=len(sphere)).astype(np.float64)


def _entropy2(p):
  p = np.asarray(p, np.float64)
  p = p[p > 0]
  return float(-(p * np.log2(p)).sum())


PAPER_JSD_EPS = 1e-8


def jsd_from_counts(p, q, protocol: str = 'reference'):
  """Base-2 JSD between two count vectors (see the module docstring)."""
  if protocol not in ('reference', 'paper'):
    raise ValueError(f'unknown protocol {protocol!r}')
  p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
  if p.sum() <= 0 or q.sum() <= 0:
    raise errors.InputError(f'JSD needs at least one point in each set, got {p.sum():g} '
                            f'and {q.sum():g}')
  p, q = p / p.sum(), q / q.sum()
  if protocol == 'paper':
    e = PAPER_JSD_EPS
    p, q = p + e, q + e
    return _entropy2((p + q) / 2 + e) - (_entropy2(p) + _entropy2(q)) / 2
  return _entropy2((p + q) / 2) - (_entropy2(p) + _entropy2(q)) / 2


def jsd(clouds_a, clouds_b, valid_a=None, valid_b=None,
        resolution: int = JSD_RESOLUTION, scale: float = 0.5,
        protocol: str = 'reference'):
  """Base-2 JSD between the grid occupancies of two sets of clouds (finite:
  errors.InputError otherwise)."""
  errors.check_finite(clouds_a, 'clouds_a')
  errors.check_finite(clouds_b, 'clouds_b')
  return jsd_from_counts(occupancy(clouds_a, valid_a, resolution, scale),
                         occupancy(clouds_b, valid_b, resolution, scale), protocol)
