"""A learned fill: a small network that chooses, for each missing pixel,
among the classical fills (interpolation.py) and, optionally, DUSty's
reconstruction x_tilde.

Interpolation is right on a smooth surface and wrong across a depth edge,
where it puts a point between the foreground and the background; there the
nearest return above, below, left or right is right, and which one depends
on the scene. The network sees the candidates, the known pixels and the
distances to them, and outputs softmax weights over the candidates: its
answer is a convex combination of them in inverse depth, so it never leaves
the range its inputs span (what keeps it sane on scans unlike its training
data). Trained on the simulator's scans (``train``), corrupted at random
(every row of K, random pixels), to minimise AbsRel on the removed returns.

Candidates per pixel: linear, the nearest return up / down / left / right
(the same column or row; linear where there is none), the nearest return.
One ships for the simulated HDL-64E (pretrained/restorers/sim-hdl64e.npz,
trained by benchmarks/research/restoration/train_restorer.py: AbsRel plus
0.05 x the cross-entropy against each pixel's best candidate, which AbsRel
alone lacked: without it the choice collapsed onto linear).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from dusty_jax import interpolation, layers
from dusty_jax.sensor import SensorSpec

DIRECTIONS = ('up', 'down', 'left', 'right')
CANDIDATES = ('linear',) + DIRECTIONS + ('nearest',)
MAX_DISTANCE = 16  # pixels; farther is "far"


@dataclasses.dataclass(frozen=True)
class Settings:
  width: int = 32

  @property
  def num_candidates(self) -> int:
    return len(CANDIDATES)


def code(depth, sensor: SensorSpec):
  """Metric depth (clipped to the sensor's range) -> [-1, 1] inverse depth,
  the codec's scale, without drops."""
  lo, hi = 1.0 / sensor.max_depth, 1.0 / sensor.min_depth
  d = np.clip(depth, sensor.min_depth, sensor.max_depth)
  return (2.0 * (1.0 / d - lo) / (hi - lo) - 1.0).astype(np.float32)


def uncode(x, sensor: SensorSpec):
  lo, hi = 1.0 / sensor.max_depth, 1.0 / sensor.min_depth
  return 1.0 / ((jnp.clip(x, -1.0, 1.0) + 1.0) / 2.0 * (hi - lo) + lo)


def features(depth, known, sensor: SensorSpec):
  """One scan's (candidates (H, W, K0), inputs (H, W, C)) for the network,
  numpy; ``depth`` metres, ``known`` bool (H, W). K0 = len(CANDIDATES).

  The candidates are in [-1, 1] inverse depth (:func:`code`); the inputs
  see them as log-ratios to linear's (a relative difference reads the same
  at 5 m and at 80 m, where inverse depth differs by little), linear's log
  depth itself, the distances to the returns each way (in MAX_DISTANCE) and
  the known and returned pixels."""
  lo, hi = sensor.min_depth, sensor.max_depth
  depth = np.where(known, depth, 0.0)
  lin = interpolation.linear(depth, known, lo, hi)
  cands, dists = [lin], []
  for direction in DIRECTIONS:
    v, dist = interpolation.directional(depth, known, lo, hi, direction)
    cands.append(np.where(np.isfinite(v), v, lin))
    dists.append(np.minimum(dist, MAX_DISTANCE) / MAX_DISTANCE)
  cands.append(interpolation.nearest(depth, known, lo, hi))
  ratios = [np.clip(np.log(c / lin), -3, 3) for c in cands[1:]]
  returned = known & (depth > lo) & (depth < hi)
  inputs = np.stack(ratios + [np.log(lin / 10.0) / 2] + dists + [known, returned], -1)
  return (np.stack([code(c, sensor) for c in cands], -1),
          inputs.astype(np.float32))


class Selector(nn.Module):
  """A two-level U-Net on the cylinder: inputs (B, H, W, C) -> logits
  (B, H, W, K). W must be a multiple of 4 (the sensor's is of 16); rows
  are padded with zeros up to a multiple of 4 and cut off again."""
  settings: Settings

  @nn.compact
  def __call__(self, x):
    w = self.settings.width
    conv = lambda h, f, k=3: nn.Conv(f, (k, k), padding='VALID')(
        layers.cylinder_pad(h, k // 2, k // 2, k // 2, k // 2))
    block = lambda h, f: nn.gelu(conv(nn.gelu(conv(h, f)), f))
    pool = lambda h: nn.avg_pool(h, (2, 2), (2, 2))
    up = lambda h: jnp.repeat(jnp.repeat(h, 2, 1), 2, 2)
    rows = x.shape[1]
    x = jnp.pad(x, [(0, 0), (0, -rows % 4), (0, 0), (0, 0)])
    h1 = block(x, w)
    h2 = block(pool(h1), 2 * w)
    h3 = block(pool(h2), 2 * w)
    h2 = block(jnp.concatenate([up(h3), h2], -1), 2 * w)
    h1 = block(jnp.concatenate([up(h2), h1], -1), w)
    return nn.Dense(self.settings.num_candidates)(h1)[:, :rows]


def combine(logits, cands):
  """The network's answer in [-1, 1] inverse depth: the softmax-weighted
  candidates."""
  return jnp.sum(jax.nn.softmax(logits, -1) * cands, -1)


@functools.partial(jax.jit, static_argnames=('settings',))
def apply(variables, inputs, cands, settings: Settings):
  """(B, H, W) inverse depth in [-1, 1] from features (B, H, W, .)."""
  return combine(Selector(settings).apply(variables, inputs), cands)


def loss_fn(variables, inputs, cands, target, mask, settings: Settings, sensor):
  """AbsRel over ``mask`` of the answer against ``target`` metres."""
  pred = uncode(apply(variables, inputs, cands, settings), sensor)
  err = jnp.abs(pred - target) / jnp.where(mask, target, 1.0)
  return jnp.sum(jnp.where(mask, err, 0.0)) / jnp.maximum(mask.sum(), 1)


# Shipped trained restorers: NAME.npz in pretrained/restorers, each for the
# sensor its meta names (its variables under 'params/...', and 'meta').
SHIPPED = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'pretrained', 'restorers')


def save(path: str, variables, settings: Settings, sensor: SensorSpec, record: dict):
  """Writes a trained restorer as one .npz: variables, settings, sensor,
  and how it was trained (``record``)."""
  flat = {'/'.join(str(getattr(k, 'key', k)) for k in p): np.asarray(v)
          for p, v in jax.tree_util.tree_leaves_with_path(variables)}
  meta = {'settings': dataclasses.asdict(settings), 'sensor': sensor.to_dict(), **record}
  np.savez(path, meta=json.dumps(meta), **flat)


def load(path: str):
  """(variables, settings, meta) of a restorer .npz."""
  with np.load(path, allow_pickle=False) as f:
    meta = json.loads(str(f['meta']))
    variables = {}
    for key in f.files:
      if key == 'meta':
        continue
      node = variables
      *parents, leaf = key.split('/')
      for p in parents:
        node = node.setdefault(p, {})
      node[leaf] = jnp.asarray(f[key])
  return variables, Settings(**meta['settings']), meta


@functools.lru_cache(maxsize=None)
def _index(folder: str) -> tuple:
  """(path, sensor as sorted JSON) of each restorer .npz in ``folder``, read
  once per folder: restore() asks for every call."""
  if not os.path.isdir(folder):
    return ()
  out = []
  for name in sorted(os.listdir(folder)):
    if name.endswith('.npz'):
      with np.load(os.path.join(folder, name), allow_pickle=False) as f:
        sensor = json.loads(str(f['meta']))['sensor']
      out.append((os.path.join(folder, name), json.dumps(sensor, sort_keys=True)))
  return tuple(out)


def shipped_for(sensor: SensorSpec) -> str | None:
  """The path of a shipped restorer trained for ``sensor``, or None."""
  want = json.dumps(sensor.to_dict(), sort_keys=True)
  return next((path for path, spec in _index(SHIPPED) if spec == want), None)


@functools.lru_cache(maxsize=4)
def _loaded(path: str):
  return load(path)


def fill(path: str, depth, known, sensor: SensorSpec):
  """The learned fill of scans (B, H, W) metres with ``known`` (B, H, W),
  by the restorer at ``path``: metres at every pixel (B, H, W)."""
  variables, settings, _ = _loaded(path)
  cands, inputs = (np.stack(v) for v in zip(*(features(d, k, sensor)
                                              for d, k in zip(depth, known))))
  x = apply(variables, jnp.asarray(inputs), jnp.asarray(cands), settings)
  return np.asarray(uncode(x, sensor), np.float32)
