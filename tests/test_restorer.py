"""The learned fill: its candidates, its convex answer, its file."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dusty_jax import interpolation, restorer
from dusty_jax.sensor import tiny_sensor

H, W = 16, 64


@pytest.fixture(scope='module')
def sensor():
  return tiny_sensor(H, W)


def scan(seed=0):
  rng = np.random.default_rng(seed)
  depth = np.where(np.arange(W) < W // 2, 8.0, 40.0) * np.ones((H, 1))
  depth = depth * rng.uniform(0.95, 1.05, (H, W))
  known = rng.uniform(size=(H, W)) < 0.3
  return depth.astype(np.float32), known


def test_features_hold_each_candidate(sensor):
  depth, known = scan()
  cands, inputs = restorer.features(depth, known, sensor)
  assert cands.shape == (H, W, len(restorer.CANDIDATES))
  assert inputs.shape == (H, W, len(restorer.CANDIDATES) + len(restorer.DIRECTIONS) + 2)
  lin = interpolation.linear(np.where(known, depth, 0.0), known, sensor.min_depth,
                             sensor.max_depth)
  np.testing.assert_allclose(restorer.uncode(cands[..., 0], sensor), lin, rtol=1e-4)
  up, _ = interpolation.directional(np.where(known, depth, 0.0), known, sensor.min_depth,
                                    sensor.max_depth, 'up')
  has = np.isfinite(up)
  np.testing.assert_allclose(np.asarray(restorer.uncode(cands[..., 1], sensor))[has],
                             up[has], rtol=1e-4)
  np.testing.assert_array_equal(inputs[..., -2], known)


def test_the_answer_stays_between_its_candidates(sensor):
  depth, known = scan(1)
  cands, inputs = restorer.features(depth, known, sensor)
  settings = restorer.Settings(width=8)
  variables = restorer.Selector(settings).init(jax.random.key(0), inputs[None])
  # Scale the weights up: sharp, arbitrary choices.
  variables = jax.tree.map(lambda v: 50 * v, variables)
  out = np.asarray(restorer.apply(variables, jnp.asarray(inputs[None]),
                                  jnp.asarray(cands[None]), settings))[0]
  assert (out >= cands.min(-1) - 1e-6).all() and (out <= cands.max(-1) + 1e-6).all()


def test_a_restorer_file_round_trips_and_is_found_by_its_sensor(sensor, tmp_path,
                                                               monkeypatch):
  depth, known = scan(2)
  cands, inputs = restorer.features(depth, known, sensor)
  settings = restorer.Settings(width=8)
  variables = restorer.Selector(settings).init(jax.random.key(1), inputs[None])
  path = str(tmp_path / 'r.npz')
  restorer.save(path, variables, settings, sensor, {'steps': 0})
  loaded, got, meta = restorer.load(path)
  assert got == settings and meta['steps'] == 0
  jax.tree.map(np.testing.assert_array_equal, loaded, variables)
  monkeypatch.setattr(restorer, 'SHIPPED', str(tmp_path))
  assert restorer.shipped_for(sensor) == path
  assert restorer.shipped_for(sensor.with_width(2 * W)) is None
  filled = restorer.fill(path, depth[None], known[None], sensor)[0]
  want = restorer.uncode(restorer.apply(variables, jnp.asarray(inputs[None]),
                                        jnp.asarray(cands[None]), settings), sensor)[0]
  np.testing.assert_allclose(filled, want, rtol=1e-6)
