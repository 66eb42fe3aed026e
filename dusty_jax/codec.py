"""The inverse-depth codec (in-graph): metric depth <-> normalised inverse depth.

Maps metric depth d to ``x`` in [-1, 1]: 1/d, with (0.9, 120) m mapped
linearly so that 120 m is -1 and 0.9 m is +1. A point-drop is the constant
ALPHA = -1. Valid means min_depth < d < max_depth strictly, so a valid pixel
always encodes strictly above ALPHA. :func:`to_points` back-projects depth
with a per-pixel angle table (data/unfolding.py estimates one). Every
function takes the sensor as a SensorSpec, resolved from a name where the
program starts, and refuses anything else with a TypeError.

jnp throughout: works inside jit and on numpy inputs (``np.asarray`` the
result for numpy).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from dusty_jax import errors
from dusty_jax.sensor import SensorSpec, check_spec

ALPHA = -1.0  # the point-drop constant in normalised inverse depth.


def check_precision(x, what: str = 'normalised inverse depth'):
  """``x`` unchanged unless its dtype is float16 or bfloat16: those are
  refused (errors.InputError) for normalised inverse depth. Rounded to them,
  a 0.9-120 m code moves returns by up to 1.1 m (float16) or 8.9 m
  (bfloat16) below 90 m, and turns every return beyond about 118 m
  (float16) or 106 m (bfloat16) into ALPHA, a drop. Metric depth
  (:func:`encode`) may come in half precision: it is cast to float32, its
  own rounding (2**-11 or 2**-8 of the depth) the only error. The dtype is
  static, so this also runs under jit."""
  dtype = np.dtype(getattr(x, 'dtype', np.float32))
  if dtype.name in errors.HALF:
    raise errors.InputError(
        f'{what} in {dtype.name}: too coarse for normalised inverse depth, where far '
        'returns round onto ALPHA (a drop) and depths move by metres; keep scans in '
        'float32 (codec.encode of metric depth returns float32)')
  return x


def valid_depth(depth, sensor: SensorSpec):
  """True where depth is finite and strictly inside the sensor's range."""
  check_spec(sensor)
  depth = jnp.asarray(depth)
  return jnp.isfinite(depth) & (depth > sensor.min_depth) & (
      depth < sensor.max_depth)


def _inv_bounds(sensor: SensorSpec):
  return 1.0 / sensor.max_depth, 1.0 / sensor.min_depth


def encode(depth, sensor: SensorSpec):
  """Metric depth (any shape) -> normalised inverse depth in [-1, 1].

  Zero, negative, NaN, inf and out-of-range depths become ALPHA, never NaN.
  Any float dtype is cast to float32 first; the result is float32.
  ``sensor``: a SensorSpec (``params.sensor``, ``sensor.PRESETS['kitti']``).
  """
  check_spec(sensor)
  depth = jnp.asarray(depth, jnp.float32)
  valid = valid_depth(depth, sensor)
  lo, hi = _inv_bounds(sensor)
  safe = jnp.where(valid, depth, sensor.max_depth)
  x = 2.0 * (1.0 / safe - lo) / (hi - lo) - 1.0
  # A valid depth just below max_depth may round to exactly ALPHA in float32;
  # keep it distinguishable from a drop.
  x = jnp.clip(x, jnp.nextafter(jnp.float32(ALPHA), jnp.float32(0)), 1.0)
  return jnp.where(valid, x, ALPHA)


def decode(x, sensor: SensorSpec, tolerance: float = 0.0):
  """Normalised inverse depth -> (metric depth, valid mask).

  A pixel counts as dropped when ``|x - ALPHA| / 2 <= tolerance`` (the
  paper's relative tolerance beta for the baseline model; 0 for DUSty, where
  only exactly ALPHA is a drop). Dropped pixels get depth 0. NaN counts as
  dropped. ``x`` in float16 or bfloat16 is refused (:func:`check_precision`).
  """
  check_spec(sensor)
  x = jnp.asarray(check_precision(x, 'x'), jnp.float32)
  valid = jnp.isfinite(x) & ((x - ALPHA) / 2.0 > tolerance)
  lo, hi = _inv_bounds(sensor)
  xc = jnp.clip(jnp.where(valid, x, 0.0), -1.0, 1.0)
  inv = (xc + 1.0) / 2.0 * (hi - lo) + lo
  return jnp.where(valid, 1.0 / inv, 0.0), valid


def complete_depth(x_tilde, sensor: SensorSpec):
  """A complete inverse depth (DUSty's x_tilde) -> metric depth everywhere.

  Unlike :func:`decode`, nothing is a drop: x_tilde = ALPHA is the far end
  of the range (max_depth), not a missing point.
  """
  check_spec(sensor)
  x = jnp.clip(jnp.asarray(x_tilde, jnp.float32), ALPHA, 1.0)
  lo, hi = _inv_bounds(sensor)
  return 1.0 / ((x + 1.0) / 2.0 * (hi - lo) + lo)


def to_points(depth, angles):
  """Back-projects depth (..., H, W) with angles (2, H, W) to (..., H, W, 3).

  jnp; dropped pixels (depth 0) land at the origin, so pair the result with
  the valid mask from :func:`decode`.
  """
  depth = jnp.asarray(depth)
  el, az = angles[0], angles[1]
  r = depth * jnp.cos(el)
  return jnp.stack([r * jnp.cos(az), r * jnp.sin(az), depth * jnp.sin(el)], -1)
