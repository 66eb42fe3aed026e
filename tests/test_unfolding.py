"""Scan unfolding (firing order, ring ids, elevations), angle tables and back-projection."""

import warnings

import numpy as np
import pytest

from conftest import random_depth, sensor_order_points
from dusty_jax import codec
from dusty_jax.data import kitti as kitti_io
from dusty_jax.data import mpo as mpo_io
from dusty_jax.data import unfolding
from dusty_jax.errors import DataError
from dusty_jax.sensor import get_sensor


def test_kitti_bin_round_trip_exact(kitti, tmp_path):
  depth = random_depth(kitti, seed=1)
  path = str(tmp_path / '000000.bin')
  kitti_io.write_bin(path, sensor_order_points(depth, kitti))
  with warnings.catch_warnings():
    warnings.simplefilter('error')  # a full scan must not warn.
    image, report = kitti_io.load_scan(path, kitti)
  assert image.shape == (64, 256)
  assert report.ring_rows == {i: i for i in range(64)}  # ring i is row i
  np.testing.assert_allclose(image, depth, rtol=1e-5, atol=0)


def test_ring_without_returns_straight_ahead(kitti):
  depth = random_depth(kitti, seed=2, drop=0.0)
  w = kitti.width
  # Ring 10 sees nothing in the front half; ring 11 nothing near the front.
  depth[10, w // 4: 3 * w // 4] = 0
  depth[11, w // 2 - 5: w // 2 + 5] = 0
  u = unfolding.unfold(sensor_order_points(depth, kitti), kitti, firing_order=True)
  assert len(u.ring_rows) == 64
  np.testing.assert_allclose(u.depth, depth, rtol=1e-5)


def test_empty_ring_mid_scan_keeps_rows(kitti):
  depth = random_depth(kitti, seed=3, drop=0.1)
  depth[30] = 0  # the sensor returned nothing for this beam at all.
  with pytest.warns(UserWarning, match=r'found 63 rings.*rows \[30\] left empty'):
    u = unfolding.unfold(sensor_order_points(depth, kitti), kitti, source='scan.bin',
                         firing_order=True)
  assert sorted(u.ring_rows.values()) == [r for r in range(64) if r != 30]
  np.testing.assert_allclose(u.depth, depth, rtol=1e-5)


def test_too_many_rings_is_an_error(tiny, kitti):
  pts = sensor_order_points(random_depth(kitti, seed=4), kitti)
  with pytest.raises(DataError, match='x.bin: found 64 rings but sensor'):
    unfolding.unfold(pts, tiny, source='x.bin', firing_order=True)
  with pytest.raises(ValueError, match='not both'):
    unfolding.unfold(pts, kitti, ring=np.zeros(len(pts)), firing_order=True)


def test_nearest_point_wins_and_xyz(kitti):
  depth = random_depth(kitti, seed=5)
  pts = sensor_order_points(depth, kitti)  # a farther return in every pixel
  u = unfolding.unfold(pts, kitti, firing_order=True)
  np.testing.assert_allclose(u.depth, depth, rtol=1e-5)
  np.testing.assert_allclose(np.linalg.norm(u.xyz, axis=-1), u.depth, rtol=1e-5)
  assert u.hidden == (depth > 0).sum() and u.placed == (depth > 0).sum()


def test_firing_order_follows_the_authors_rule(kitti):
  """Every point competes for its pixel whatever its range (the authors
  mask the range after the projection): a return nearer than min_depth
  hides a valid one and leaves its pixel invalid, one at the origin empties
  its pixel, one beyond max_depth stays. Without the firing order
  out-of-range returns are dropped first."""
  depth = random_depth(kitti, seed=12, drop=0.0)
  pts = sensor_order_points(depth, kitti, extra_offgrid=False)
  ring_of = np.repeat(np.arange(64), kitti.width)
  near, origin = 5, 7  # rows
  i = np.flatnonzero(ring_of == near)[100]  # its ring's 101st point, column 27
  j = np.flatnonzero(ring_of == origin)[0]  # its ring's first point
  col = kitti.column_of(np.arctan2(pts[i, 1], pts[i, 0]))[0]
  close = pts[i].copy()
  close[:3] *= 0.3 / np.linalg.norm(close[:3])
  # Right after its pixel's return, and at the start of a ring (azimuth 0,
  # column 128): neither moves a ring break.
  pts = np.insert(pts, [i + 1, j], [close, np.zeros(4, np.float32)], axis=0)
  u = unfolding.unfold(pts, kitti, firing_order=True)
  assert u.ring_rows == {r: r for r in range(64)}
  want = depth.copy()
  want[near, col], want[origin, 128] = 0.3, 0.0
  np.testing.assert_allclose(u.depth, want, rtol=1e-5)
  assert u.out_of_range == 1 and u.no_return == 1 and u.hidden == 2
  bare = unfolding.unfold(pts, kitti)  # rows from the elevations: range first
  np.testing.assert_allclose(bare.depth, depth, rtol=1e-5)
  assert bare.out_of_range == 1 and bare.no_return == 1 and bare.hidden == 0
  pts[0, :3] *= 150 / np.linalg.norm(pts[0, :3])  # stays in ring 0, out of range
  u = unfolding.unfold(pts, kitti, firing_order=True)
  assert u.depth.max() == pytest.approx(150, rel=1e-6) and u.out_of_range == 2


def test_unfold_by_elevation_without_ring_order(kitti):
  """A shuffled sweep (no ring order, no ring field): each point on its
  nearest beam; points beyond half a beam spacing above the top beam or
  below the bottom beam are dropped, and counted."""
  depth = random_depth(kitti, seed=6)
  pts = sensor_order_points(depth, kitti, extra_offgrid=False)
  rng = np.random.default_rng(0)
  shuffled = pts[rng.permutation(len(pts))]  # no ring order needed.
  u = unfolding.unfold(shuffled, kitti)
  np.testing.assert_allclose(u.depth, depth, rtol=1e-5)
  assert u.ring_rows is None and u.placed == (depth > 0).sum()
  spacing = np.abs(np.diff(kitti.elevation))
  off = []
  for el in (kitti.elevation[0] + 0.6 * spacing[0], kitti.elevation[-1] - 0.6 * spacing[-1]):
    off.append([10 * np.cos(el), 0, 10 * np.sin(el), 0])
  inner = kitti.elevation[0] + 0.4 * spacing[0]  # inside the margin: the top row
  off.append([20 * np.cos(inner), 0, 20 * np.sin(inner), 0])
  u = unfolding.unfold(np.concatenate([shuffled, np.float32(off)]), kitti)
  assert u.off_elevation == 2
  want = depth.copy()
  col = kitti.column_of(np.zeros(1))[0][0]  # azimuth 0
  want[0, col] = min(20, depth[0, col]) if depth[0, col] else 20
  np.testing.assert_allclose(u.depth, want, rtol=1e-5)


def test_mpo_ring_ids_in_any_numbering(tmp_path):
  """MPO's ring ids (ring 0 the lowest beam) go through unfold's ring
  field: the rows follow the rings' elevations, whatever their numbering."""
  mpo = get_sensor('mpo')
  depth = random_depth(mpo, seed=7)
  pts = sensor_order_points(depth, mpo, extra_offgrid=False)[:, :3]
  el = np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1]))
  row = np.argmin(np.abs(el[:, None] - mpo.elevation[None]), axis=1)
  ring = mpo.height - 1 - row  # ring 0 is the lowest beam.
  for i, ids in enumerate((ring, ring + 1, (7 * ring) % 32)):
    path = tmp_path / f'class0_set001_scan{i:05d}.npy'
    np.save(path, np.concatenate([pts, ids[:, None].astype(np.float32)], 1))
    image, u = mpo_io.load_scan(str(path), mpo)
    np.testing.assert_allclose(image, depth, rtol=1e-5)
    assert sorted(u.ring_rows.values()) == list(range(32))
  split = np.where((row == 0) & (np.arange(len(row)) % 2 == 0), 99, row)  # 33 ids
  path = str(tmp_path / 'f.npy')
  np.save(path, np.concatenate([pts, split[:, None]], 1))
  with pytest.raises(DataError, match=r"f\.npy: 33 distinct ring ids, but sensor 'mpo' has 32"):
    mpo_io.load_scan(path, mpo)
  np.save(path, np.concatenate([pts, row[:, None] + 0.5], 1))
  with pytest.raises(DataError, match=r'f\.npy: the ring field holds values that are not'):
    mpo_io.load_scan(path, mpo)


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
    (np.zeros((0, 4), np.float32), 'bad.bin: the scan has no points'),
    (np.zeros((5, 2), np.float32), r'bad.bin: expected an \(N, >=3\)'),
    ({'x': np.zeros(3), 'y': np.zeros(3)}, r"bad.bin: no 'z' field among \['x', 'y'\]"),
])
def test_bad_points(kitti, points, match):
  for firing_order in (False, True):
    with pytest.raises(DataError, match=match):
      unfolding.unfold(points, kitti, source='bad.bin', firing_order=firing_order)


def test_nan_points(kitti):
  """NaN or inf: a placeholder of a beam without a return in a point file,
  a broken file in firing order (KITTI's reader refuses it too)."""
  pts = sensor_order_points(random_depth(kitti, seed=10), kitti)
  pts[3, 1], pts[7, 2] = np.nan, np.inf
  with pytest.raises(DataError, match='bad.bin: 2 of .* points have NaN or inf'):
    unfolding.unfold(pts, kitti, source='bad.bin', firing_order=True)
  u = unfolding.unfold(pts, kitti, source='bad.bin')
  assert u.no_return == 2 and np.isfinite(u.depth).all()


def test_a_sweep_without_a_return(kitti):
  """A point file of placeholders only is refused in one line; in firing
  order (KITTI) it is the authors' empty image, which prepare skips."""
  empty = np.zeros((100, 3))
  empty[::2] = np.nan
  with pytest.raises(DataError, match=r'^e\.pcd: none of its 100 points is a return'):
    unfolding.unfold(empty, kitti, source='e.pcd')
  u = unfolding.unfold(np.zeros((100, 3)), kitti, source='e.bin', firing_order=True)
  assert u.placed == 0 and not u.depth.any()
