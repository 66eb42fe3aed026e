"""Inverse-depth codec: round trips, extremes, and the drop constant."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dusty_jax import codec
from dusty_jax.codec import ALPHA


def test_endpoints_match_paper(kitti):
  x = np.asarray(codec.encode(np.array([0.9 + 1e-4, 119.999, 10.0]), kitti))
  assert x[0] == pytest.approx(1.0, abs=3e-4) and x[0] < 1.0
  assert x[1] == pytest.approx(-1.0, abs=1e-5) and x[1] > ALPHA
  # Independent float64 computation of the linear map of 1/d.
  lo, hi = 1 / 120, 1 / 0.9
  assert x[2] == pytest.approx(2 * (0.1 - lo) / (hi - lo) - 1, abs=1e-6)


def test_round_trip_random_depths(kitti):
  rng = np.random.default_rng(0)
  # Log-uniform over the whole valid range, including both ends.
  d = np.exp(rng.uniform(np.log(0.9), np.log(120), 100_000)).astype(np.float32)
  d = np.concatenate([d, np.float32([0.9 + 1e-3, 119.99, 1.0, 60.0])])
  d = d[(d > 0.9) & (d < 120)]
  x = codec.encode(d, kitti)
  back, valid = codec.decode(x, kitti)
  assert bool(jnp.all(valid)), 'every valid depth must decode as valid'
  np.testing.assert_allclose(np.asarray(back), d, rtol=2e-5)
  assert float(jnp.min(x)) > ALPHA and float(jnp.max(x)) <= 1.0


@pytest.mark.parametrize('bad', [0.0, -3.0, 0.9, 120.0, 500.0, np.nan, np.inf,
                                 -np.inf, 0.5])
def test_invalid_depth_is_dropped(kitti, bad):
  x = codec.encode(np.float32([bad, 10.0]), kitti)
  assert float(x[0]) == ALPHA
  assert np.isfinite(np.asarray(x)).all()
  d, valid = codec.decode(x, kitti)
  assert not bool(valid[0]) and float(d[0]) == 0.0 and bool(valid[1])


def test_decode_tolerance_and_nan(kitti):
  x = jnp.array([ALPHA, ALPHA + 0.01, ALPHA + 0.03, jnp.nan, 2.0])
  _, valid = codec.decode(x, kitti, tolerance=0.008)
  # |x - alpha| / 2 <= beta is a drop: 0.005 <= 0.008 dropped, 0.015 kept.
  assert valid.tolist() == [False, False, True, False, True]
  d, _ = codec.decode(x, kitti)
  assert np.isfinite(np.asarray(d)).all()
  assert float(d[4]) == pytest.approx(0.9, rel=1e-6)  # clipped to min range.


def test_encode_gradient_finite_at_extremes(kitti):
  d = jnp.array([0.0, 0.9, 1e-30, 119.9999, 120.0, 1e30, jnp.inf, jnp.nan])
  g = jax.grad(lambda d: codec.encode(d, kitti).sum())(d)
  assert np.isfinite(np.asarray(g)).all()


def test_complete_depth_reads_alpha_as_max_range(kitti):
  """x_tilde is complete: ALPHA is 120 m there, not a drop (decode's 0)."""
  from dusty_jax import codec
  d = np.array([1.0, 5.0, 30.0, 119.0], np.float32)
  np.testing.assert_allclose(
      np.asarray(codec.complete_depth(codec.encode(d, kitti), kitti)), d,
      rtol=1e-4)
  ends = np.asarray(codec.complete_depth(np.array([-1.0, 1.0, -3.0]), kitti))
  np.testing.assert_allclose(ends, [kitti.max_depth, kitti.min_depth, kitti.max_depth],
                             rtol=1e-5)


def test_reconstruction_errors_of_a_far_x_tilde(tiny):
  """A target at 119 m reconstructed as x_tilde = -1 (120 m) is nearly exact."""
  from dusty_jax.metrics import reconstruction
  target = np.full((1,) + tiny.shape, 119.0, np.float32)
  x = -np.ones((1,) + tiny.shape, np.float32)
  pts = np.zeros((1,) + tiny.shape + (3,), np.float32)
  res = {'inv_depth': x, 'points': pts, 'valid': np.zeros((1,) + tiny.shape, bool)}
  errs = reconstruction.errors(target, res, np.asarray(tiny.nominal_angles()), tiny)
  assert errs['abs_rel'][0] == pytest.approx(1 / 119, rel=1e-3)
