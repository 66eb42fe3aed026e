"""Scan unfolding, spherical projection, angle tables and back-projection."""

import warnings

import numpy as np
import pytest

from conftest import random_depth, sensor_order_points
from dusty_jax import codec
from dusty_jax.data import kitti as kitti_io
from dusty_jax.data import unfolding


def test_kitti_bin_round_trip_exact(kitti, tmp_path):
  depth = random_depth(kitti, seed=1)
  path = str(tmp_path / '000000.bin')
  kitti_io.write_bin(path, sensor_order_points(depth, kitti))
  with warnings.catch_warnings():
    warnings.simplefilter('error')  # a full scan must not warn.
    image, report = kitti_io.load_scan(path, kitti)
  assert image.shape == (64, 256)
  assert report.ok and not report.matched_by_elevation
  np.testing.assert_allclose(image, depth, rtol=1e-5, atol=0)


def test_ring_without_returns_straight_ahead(kitti):
  depth = random_depth(kitti, seed=2, drop=0.0)
  w = kitti.width
  # Ring 10 sees nothing in the front half; ring 11 nothing near the front.
  depth[10, w // 4: 3 * w // 4] = 0
  depth[11, w // 2 - 5: w // 2 + 5] = 0
  image, report = unfolding.unfold_scan(sensor_order_points(depth, kitti), kitti)
  assert report.ok
  np.testing.assert_allclose(image, depth, rtol=1e-5)


def test_empty_ring_mid_scan_keeps_rows(kitti):
  depth = random_depth(kitti, seed=3, drop=0.1)
  depth[30] = 0  # the sensor returned nothing for this beam at all.
  with pytest.warns(UserWarning, match=r'found 63 rings.*rows \[30\] left empty'):
    image, report = unfolding.unfold_scan(
        sensor_order_points(depth, kitti), kitti, source='scan.bin')
  assert report.rings_found == 63 and report.matched_by_elevation
  np.testing.assert_allclose(image, depth, rtol=1e-5)


def test_too_many_rings_is_an_error(tiny, kitti):
  pts = sensor_order_points(random_depth(kitti, seed=4), kitti)
  with pytest.raises(ValueError, match='found 64 rings but sensor'):
    unfolding.unfold_scan(pts, tiny, source='x.bin')


def test_nearest_point_wins_and_xyz(kitti):
  depth = random_depth(kitti, seed=5)
  pts = sensor_order_points(depth, kitti)
  image, xyz, _ = unfolding.unfold_scan(pts, kitti, return_xyz=True)
  np.testing.assert_allclose(np.linalg.norm(xyz, axis=-1), image, rtol=1e-5)


def test_spherical_projection_matches_unfolding(kitti):
  depth = random_depth(kitti, seed=6)
  pts = sensor_order_points(depth, kitti, extra_offgrid=False)
  rng = np.random.default_rng(0)
  shuffled = pts[rng.permutation(len(pts))]  # no ring order needed.
  image = unfolding.spherical_projection(shuffled, kitti)
  np.testing.assert_allclose(image, depth, rtol=1e-5)


def test_unfold_rings_mpo_convention():
  from dusty_jax.sensor import get_sensor
  mpo = get_sensor('mpo')
  depth = random_depth(mpo, seed=7)
  pts = sensor_order_points(depth, mpo, extra_offgrid=False)
  el = np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1]))
  row = np.argmin(np.abs(el[:, None] - mpo.elevation[None]), axis=1)
  ring = mpo.height - 1 - row  # ring 0 is the lowest beam.
  image = unfolding.unfold_rings(pts, ring, mpo)
  np.testing.assert_allclose(image, depth, rtol=1e-5)
  with pytest.raises(ValueError, match='ring ids span'):
    unfolding.unfold_rings(pts, ring + 1, mpo, source='f.npy')


def test_angle_table_estimate_and_fallbacks(tiny):
  depth = random_depth(tiny, seed=8, drop=0.3)
  depth[:, 5] = 0   # a column never valid -> column mean azimuth.
  depth[2] = 0      # a row never valid -> nominal elevation of that row.
  angles_true = tiny.nominal_angles()
  xyz = np.asarray(codec.to_points(depth, angles_true))
  est = unfolding.estimate_angles([xyz, xyz], tiny)
  valid = depth > 0
  np.testing.assert_allclose(est[:, valid], angles_true[:, valid], atol=1e-5)
  np.testing.assert_allclose(est[0, 2], tiny.elevation[2], atol=1e-6)
  # Column 0 straddles azimuth +-pi: the circular mean must stay near pi.
  assert np.all(np.abs(np.abs(est[1, :, 0]) - np.pi) < 0.05)
  assert np.isfinite(est).all()


def test_back_projection_round_trip(tiny):
  depth = random_depth(tiny, seed=9)
  angles = tiny.nominal_angles()
  pts = np.asarray(codec.to_points(depth, angles))
  np.testing.assert_allclose(np.linalg.norm(pts, axis=-1), depth, rtol=1e-5,
                             atol=1e-6)
  x = codec.encode(depth, tiny)
  d, valid = codec.decode(x, tiny)
  assert (np.asarray(valid) == (depth > 0)).all()


@pytest.mark.parametrize('points, match', [
    (np.zeros((0, 4), np.float32), 'no points'),
    (np.float32([[np.nan, 0, 0, 0], [1, 1, 1, 0]]), 'NaN or inf'),
    (np.zeros((5, 2), np.float32), r'expected an \(N, >=3\)'),
])
def test_bad_points(kitti, points, match):
  with pytest.raises(ValueError, match=match):
    unfolding.unfold_scan(points, kitti, source='bad.bin')
