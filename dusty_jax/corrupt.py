"""Seeded corruptions of scans, for restoration experiments.

All take and return (B, H, W) normalised inverse depth with ALPHA for drops.
  * ``drop``: each valid point dropped with probability ``fraction``;
  * ``beams``: keep 1 of every ``k`` rings (a cheaper sensor), others dropped;
  * ``noise``: Gaussian noise on the range of valid points, ``sigma`` as a
    fraction of the sensor's depth range (max - min): the paper's N(0, 0.01)
    on depth normalised to [0, 1], 1.19 m for KITTI. A point pushed outside
    the sensor's range becomes a drop.
Specs as strings for the CLI: ``drop:0.9``, ``beams:8``, ``noise:0.05``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from dusty_jax import codec
from dusty_jax.codec import ALPHA
from dusty_jax.sensor import SensorSpec


def drop(key, scan, fraction: float):
  keep = jax.random.uniform(key, scan.shape) >= fraction
  return jnp.where(keep, scan, ALPHA)


def beams(scan, k: int, offset: int = 0):
  rows = (jnp.arange(scan.shape[-2]) % k) == offset
  return jnp.where(rows[:, None], scan, ALPHA)


def kept(spec: str, key, shape):
  """The pixels a corruption keeps (bool, ``shape``): what a restoration
  may treat as known. ``noise`` keeps every pixel (and moves it)."""
  name, v = parse(spec)
  if name == 'drop':  # as drop()
    return jax.random.uniform(key, shape) >= v
  if name == 'beams':
    rows = (jnp.arange(shape[-2]) % int(v)) == 0
    return jnp.broadcast_to(rows[:, None], shape)
  return jnp.ones(shape, bool)


def removes(spec: str) -> bool:
  """Whether a corruption removes pixels (so that filling them is the task)."""
  return parse(spec)[0] in ('drop', 'beams')


def noise(key, scan, sigma: float, sensor: SensorSpec):
  depth, valid = codec.decode(scan, sensor)
  span = sensor.max_depth - sensor.min_depth
  noisy = depth + sigma * span * jax.random.normal(key, scan.shape)
  return jnp.where(valid, codec.encode(noisy, sensor), ALPHA)


def parse(spec: str):
  """'drop:0.9' -> ('drop', 0.9), checking the name and the value."""
  name, _, value = spec.partition(':')
  try:
    v = float(value)
  except ValueError:
    raise ValueError(f'corruption {spec!r}: expected NAME:VALUE, e.g. drop:0.9, '
                     'beams:8, noise:0.05') from None
  if name == 'drop' and not 0 <= v < 1:
    raise ValueError(f'corruption {spec!r}: drop fraction must be in [0, 1)')
  if name == 'beams' and (v < 1 or v != int(v)):
    raise ValueError(f'corruption {spec!r}: beams takes a whole number k >= 1')
  if name == 'noise' and v < 0:
    raise ValueError(f'corruption {spec!r}: noise sigma (a fraction of the sensor\'s '
                     'depth range, not metres) must be >= 0')
  if name not in ('drop', 'beams', 'noise'):
    raise ValueError(f'unknown corruption {name!r}; known: drop, beams, noise')
  return name, v


def apply(spec: str, key, scan, sensor: SensorSpec):
  name, v = parse(spec)
  if name == 'drop':
    return drop(key, scan, v)
  if name == 'beams':
    return beams(scan, int(v))
  return noise(key, scan, v, sensor)
