"""Sweeps shaped like each maker's (issue 65): nuScenes' HDL-32E with its
placeholders near the origin and upper rings that see mostly sky, and
Ouster's beam-origin offsets, elevation tables (uniform, below the horizon,
denser near it), dual returns and placeholders at the beam origins. Rows
from a ring field and estimated specs are checked against the tables the
sweeps were simulated from."""

import dataclasses

import numpy as np
import pytest

from dusty_jax.data import estimate, simulated_lidar, unfolding
from dusty_jax.errors import DataError
from dusty_jax.sensor import PRESETS, SensorSpec

# The bounds: rows right for this share of in-range returns, and
# estimated elevations this close (degrees) to each ring's own points.
ROWS_RIGHT = 0.999
WITHIN_DEG = 0.05


def _rendered(spec, seed):
  """The simulator's observed ranges (0: no return) for ``spec``."""
  return np.asarray(simulated_lidar.render_arrays((seed, spec))[0], np.float64)


def nuscenes_like(seed=0):
  """(spec, xyz, ring ids, true rows) of an HDL-32E sweep as nuScenes
  writes it: ring ids in firing order (upper and lower beams alternate),
  elevations jittered 0.01 degrees (its motion compensation), and for each
  firing without a return a placeholder 2-5 cm out at -3 to 0 degrees."""
  spec = PRESETS['hdl32e']
  rng = np.random.default_rng(seed)
  depth = _rendered(spec, seed)
  el, az = spec.nominal_angles().astype(np.float64)
  hit = depth > 0
  el = el + np.where(hit, np.deg2rad(rng.normal(0, 0.01, el.shape)), 0)
  el = np.where(hit, el, np.deg2rad(rng.uniform(-3, 0, el.shape)))
  r = np.where(hit, depth, rng.uniform(0.02, 0.05, depth.shape))
  xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                  r * np.sin(el)], -1).reshape(-1, 3)
  rows = np.repeat(np.arange(spec.height), spec.width)
  firing_order = np.argsort(np.r_[np.arange(0, 32, 2), np.arange(1, 32, 2)])
  return spec, xyz, firing_order[rows], rows


# Ouster's tables (beam_altitude_angles, top first) and beam-origin offsets
# (lidar_origin_to_beam_origin_mm) by model and beam configuration.
def _gradient(n, half):
  u = np.linspace(1, -1, n)
  return half * np.sign(u) * np.abs(u) ** 1.6  # denser near the horizon


OUSTER = {
    'os0-32': (np.linspace(45, -45, 32), 27.67),
    'os0-128': (np.linspace(45, -45, 128), 27.67),
    'os1-32-uniform': (np.linspace(22.5, -22.5, 32), 15.806),
    'os1-32-below-horizon': (np.linspace(0, -22.5, 32), 15.806),
    'os1-64-gradient': (_gradient(64, 22.5), 15.806),
    'os1-128': (np.linspace(21, -22, 128), 15.806),
    'os2-32': (np.linspace(11.25, -11.25, 32), 13.762),
    'os2-128': (np.linspace(11.25, -11.25, 128), 13.762),
}
OUSTER_COLUMNS = 512


def ouster_like(model, seed=0, person=True):
  """(xyz, ring ids (top first), true elevations (degrees), true offsets b)
  of an Ouster sweep, each point computed as Ouster's software manual does:
  a beam starts at n from the lidar origin towards its encoder angle and
  leaves at its own azimuth offset; dual returns (30% of firings), a person
  0.5-2.5 m away across 60 columns (with ``person``; without, the upper
  beams see mostly sky), and for each firing without a return the driver's
  placeholder at the beam origin (range 0)."""
  table, n_mm = OUSTER[model]
  unit = np.random.default_rng(len(table))  # one unit's calibration, every sweep
  el = np.sort(np.asarray(table) + unit.normal(0, 0.01, len(table)))[::-1]
  h, w, n = len(el), OUSTER_COLUMNS, n_mm / 1000
  beam_az = np.resize([4.2, 1.4, -1.4, -4.2], h) + unit.normal(0, 0.02, h)
  rng = np.random.default_rng(seed)
  spec = SensorSpec(model, tuple(el), width=w, native_width=w, min_depth=0.3,
                    azimuth_offset_deg=tuple(-beam_az))
  depth = _rendered(spec, seed)
  if person:
    near = depth[:, rng.integers(0, w - 60):][:, :60]
    near[:] = np.where(rng.random(near.shape) < 0.9, rng.uniform(0.5, 2.5, 60), 0)
  encoder = 2 * np.pi * (1 - np.arange(w) / w)
  theta = encoder + np.deg2rad(-beam_az)[:, None]
  phi = np.deg2rad(el)[:, None]

  def points(measured):  # the manual's equations, range measured from the beam origin
    r = measured - n
    return np.stack([r * np.cos(theta) * np.cos(phi) + n * np.cos(encoder),
                     r * np.sin(theta) * np.cos(phi) + n * np.sin(encoder),
                     r * np.sin(phi) + 0 * theta], -1)

  hit = depth > 0
  first = points(np.where(hit, depth + n, 0.0))
  second = hit & (rng.random(hit.shape) < 0.3)
  later = points(np.where(second, depth + n + rng.uniform(0.5, 20, hit.shape), 0.0))
  ring = np.broadcast_to(np.arange(h)[:, None], hit.shape)
  xyz = np.concatenate([first[hit], later[second], first[~hit]])
  ids = np.concatenate([ring[hit], ring[second], ring[~hit]])
  return xyz, ids, el, -n * np.sin(phi[:, 0]) * np.cos(phi[:, 0])


def _in_range(xyz, spec):
  r = np.linalg.norm(xyz, axis=1)
  return (r > spec.min_depth) & (r < spec.max_depth)


def _ring_residuals_deg(xyz, rows, spec):
  """Per row of ``spec``: the median over its in-range points of their
  elevation less the spec's model of it (sin = sin(el) + b / range)."""
  r = np.linalg.norm(xyz, axis=1)
  use = _in_range(xyz, spec)
  model = np.sin(spec.elevation)[rows] + spec.vertical_offset[rows] / r
  err = np.rad2deg(np.arcsin(xyz[:, 2] / r) - np.arcsin(np.clip(model, -1, 1)))
  return np.array([np.median(err[use & (rows == j)]) for j in np.unique(rows[use])])


# --- nuScenes: placeholders near the origin, upper rings in the sky -------------

def test_nuscenes_rings_take_the_elevation_of_their_in_range_returns():
  spec, xyz, ring, rows = nuscenes_like()
  r = np.linalg.norm(xyz, axis=1)
  el = np.rad2deg(np.arcsin(xyz[:, 2] / r))
  # The trap is set: on the top ring the placeholders outnumber the returns,
  # so the median of all its points lies degrees off its beam.
  assert abs(np.median(el[rows == 0]) - spec.elevation_deg[0]) > 5
  u = unfolding.unfold(xyz, spec, ring=ring, source='nuscenes.pcd.bin')
  row = np.array([u.ring_rows[int(i)] for i in ring])
  use = _in_range(xyz, spec)
  assert np.mean(row[use] == rows[use]) >= ROWS_RIGHT  # measured 100.00%
  assert sorted(u.ring_rows.values()) == list(range(32))
  assert u.no_return == 0 and u.out_of_range == int((~use).sum())
  assert u.off_elevation == 0


@pytest.mark.parametrize('ring_field', [True, False])
def test_nuscenes_estimate_ignores_placeholders(ring_field):
  spec, xyz, ring, rows = nuscenes_like(seed=1)
  fit = estimate.estimate([xyz], ring=[ring if ring_field else None])
  assert fit.spec.height == 32
  np.testing.assert_allclose(fit.spec.elevation_deg, spec.elevation_deg, atol=WITHIN_DEG)
  assert np.abs(_ring_residuals_deg(xyz, rows, fit.spec)).max() <= WITHIN_DEG
  assert fit.near == int((np.linalg.norm(xyz, axis=1) < estimate.FIT_MIN_RANGE).sum())
  # Its range starts beyond the placeholders: unfolded with the estimate,
  # each in-range return lands in its own row.
  assert fit.spec.min_depth > 0.05
  u = unfolding.unfold(xyz, fit.spec, ring=ring if ring_field else None)
  use = _in_range(xyz, fit.spec)
  if ring_field:
    row = np.array([u.ring_rows[int(i)] for i in ring])
  else:
    r = np.linalg.norm(xyz, axis=1)
    row, _ = unfolding.nearest_beam(xyz[:, 2] / r, r, fit.spec)
  assert np.mean(row[use] == rows[use]) >= ROWS_RIGHT


def test_a_nuscenes_ring_of_placeholders_only_is_left_out_and_said():
  spec, xyz, ring, rows = nuscenes_like(seed=2)
  r = np.linalg.norm(xyz, axis=1)
  keep = (rows != 0) | (r < 0.1)  # the top beam saw only sky
  xyz, ring, rows = xyz[keep], ring[keep], rows[keep]
  fit = estimate.estimate([xyz], ring=[ring], sources=['top.pcd.bin'])
  # Its ids are not in elevation order: the ring cannot be interpolated.
  assert fit.spec.height == 31 and fit.rings_left_out == [int(ring[rows == 0][0])]
  assert f'rings {fit.rings_left_out} left out: no return beyond 0.5 m' in fit.summary()
  np.testing.assert_allclose(fit.spec.elevation_deg, spec.elevation_deg[1:], atol=WITHIN_DEG)
  u = unfolding.unfold(xyz, fit.spec, ring=ring)
  row = np.array([u.ring_rows[int(i)] for i in ring])
  use = _in_range(xyz, fit.spec)
  assert u.ring_rows[fit.rings_left_out[0]] == -1
  assert np.mean(row[use] == rows[use] - 1) >= ROWS_RIGHT


# --- Ouster: beam-origin offsets, its tables, dual returns, the sky -------------

@pytest.mark.parametrize('model, person', [(m, True) for m in sorted(OUSTER)] + [
    ('os0-128', False), ('os1-64-gradient', False)])
def test_ouster_estimate_without_a_ring_field(model, person):
  xyz, ring, el, b = ouster_like(model, person=person)
  fit = estimate.estimate([xyz], name=model)
  r = np.linalg.norm(xyz, axis=1)
  returns = np.bincount(ring[r >= estimate.FIT_MIN_RANGE], minlength=len(el))
  # Each beam found is one of the table's, with its beam origin's offset.
  el_found = np.asarray(fit.spec.elevation_deg)
  beam = np.abs(el_found[:, None] - el).argmin(1)
  np.testing.assert_allclose(el_found, el[beam], atol=WITHIN_DEG)
  np.testing.assert_allclose(fit.spec.vertical_offset_m, b[beam], atol=1e-3)
  # Every beam with a few returns beyond the placeholders is found: all of
  # them with the person near; with the sky empty (the top beams return a
  # point or two, or none) those with SPIKE_RETURNS or more.
  assert len(set(beam)) == len(beam)
  assert set(beam) >= set(np.flatnonzero(returns >= estimate.SPIKE_RETURNS))
  assert person or returns[returns > 0].min() < 10  # (the sky is empty)
  # Each in-range return of the beams found lands in its own beam's row.
  row_of_beam = np.full(len(el), -1)
  row_of_beam[beam] = np.arange(len(beam))
  row, _ = unfolding.nearest_beam(xyz[:, 2] / r, r, fit.spec)
  use = _in_range(xyz, fit.spec) & (row_of_beam[ring] >= 0)
  assert np.mean(row[use] == row_of_beam[ring[use]]) >= ROWS_RIGHT
  assert np.abs(_ring_residuals_deg(xyz[use], row_of_beam[ring[use]], fit.spec)).max() \
      <= WITHIN_DEG


@pytest.mark.parametrize('model, person', [
    ('os0-128', False), ('os1-32-below-horizon', True), ('os2-128', True)])
def test_ouster_estimate_and_rows_with_its_ring_field(model, person):
  xyz, ring, el, b = ouster_like(model, person=person)
  fit = estimate.estimate([{'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2], 'ring': ring}])
  # Every beam, those that saw only sky (their placeholders only)
  # interpolated from the ring ids, with their neighbours' offsets.
  assert fit.spec.height == len(el)
  r = np.linalg.norm(xyz, axis=1)
  measured = np.bincount(ring[r >= estimate.FIT_MIN_RANGE], minlength=len(el)) > 0
  assert fit.beams_inferred == np.flatnonzero(~measured).tolist()
  assert person or len(fit.beams_inferred) >= 10
  np.testing.assert_allclose(fit.spec.vertical_offset_m, b, atol=2e-3)
  np.testing.assert_allclose(np.asarray(fit.spec.elevation_deg)[measured], el[measured],
                             atol=WITHIN_DEG)
  u = unfolding.unfold(xyz, fit.spec, ring=ring)
  row = np.array([u.ring_rows[int(i)] for i in ring])
  use = _in_range(xyz, fit.spec)
  assert np.mean(row[use] == ring[use]) >= ROWS_RIGHT
  assert np.abs(_ring_residuals_deg(xyz[use], ring[use], fit.spec)).max() <= WITHIN_DEG


# --- Velodyne: each laser's own vertical offset -----------------------------------

def hdl64e_like(seed=0):
  """(spec, xyz, true rows, true offsets b) of an HDL-64E sweep as its
  driver computes it: each laser's vertical offset (its calibration's
  vert_offset_correction, about 0.2 m on the upper block and 0.15 m on the
  lower, a centimetre apart from laser to laser) added to z, so that
  sin(elevation) = sin(el) + v cos^2(el) / range to first order."""
  spec = dataclasses.replace(PRESETS['hdl64e'], width=PRESETS['hdl64e'].native_width)
  unit = np.random.default_rng(64)
  v = np.r_[np.full(32, 0.2), np.full(32, 0.15)] + unit.normal(0, 0.01, 64)
  depth = _rendered(spec, seed)
  hit = depth > 0
  xyz = depth[..., None] * simulated_lidar.ray_directions(spec)
  xyz[..., 2] += v[:, None]
  return spec, xyz[hit], np.nonzero(hit)[0], v * np.cos(spec.elevation) ** 2


@pytest.mark.parametrize('seed', [0, 4, 5] + [pytest.param(s, marks=pytest.mark.slow)
                                            for s in (1, 2, 3, 6, 7)])
def test_velodyne_vertical_offsets_estimate_without_a_ring_field(seed):
  # Seeds 4 and 5 have 1,700-6,300 returns within 3 m, where these offsets
  # make neighbouring beams' lines cross: fitted without them.
  spec, xyz, rows, b = hdl64e_like(seed)
  fit = estimate.estimate([xyz])
  assert fit.spec.height == 64
  r = np.linalg.norm(xyz, axis=1)
  assert fit.spec.min_depth <= r.min()  # the near returns still in range
  assert fit.near == np.sum(r < fit.fit_from)
  if seed in (4, 5):
    assert fit.near > 1000 and fit.fit_from > 3
    assert f'{fit.near} returns nearer than {fit.fit_from:.2f} m not fitted' in fit.summary()
  np.testing.assert_allclose(fit.spec.elevation_deg, spec.elevation_deg, atol=WITHIN_DEG)
  # Offsets of 150-200 mm to 5 mm (the lowest beams see the ground at
  # nearly one range, which leaves theirs loose).
  np.testing.assert_allclose(fit.spec.vertical_offset_m, b, atol=5e-3)
  row, _ = unfolding.nearest_beam(xyz[:, 2] / r, r, fit.spec)
  use = _in_range(xyz, fit.spec) & (r >= fit.fit_from)
  assert np.mean(row[use] == rows[use]) >= ROWS_RIGHT
  assert np.abs(_ring_residuals_deg(xyz[use], rows[use], fit.spec)).max() <= WITHIN_DEG
  # Nearer, the line model itself (with the true offsets) misplaces some.
  true = dataclasses.replace(spec, vertical_offset_m=tuple(float(v) for v in b))
  near = _in_range(xyz, fit.spec) & (r < fit.fit_from)
  true_row, _ = unfolding.nearest_beam(xyz[:, 2] / r, r, true)
  assert np.sum(row[near] != rows[near]) <= np.sum(true_row[near] != rows[near])


# --- What cannot be fitted: one line ---------------------------------------------

def test_a_sweep_of_placeholders_only_says_so_in_one_line():
  _, xyz, ring, rows = nuscenes_like()
  near = xyz[np.linalg.norm(xyz, axis=1) < 0.1]
  with pytest.raises(DataError, match=(
      r'^a\.pcd\.bin: only 0 returns beyond 0\.5 m to estimate a sensor from \([\d]+ nearer: '
      r'placeholders of beams without a return\?\); a sweep has thousands$')):
    estimate.estimate([near], sources=['a.pcd.bin'])


def test_sparse_noise_is_no_sensor_in_one_line():
  # Too few points for the clusters to say so (each "beam" a few points):
  # the azimuth spacing within the beams found does.
  noise = np.random.default_rng(0).normal(0, 5, (3000, 3))
  with pytest.raises(DataError, match=(
      r'^noise\.bin: no beam structure found: the returns of one beam lie [\d.]+ degrees '
      r'apart in azimuth on the median \(\d+ per revolution\), where a spinning LiDAR fires '
      r'at least 64 times a revolution; not a LiDAR sweep, or one thinned out\? Give its '
      r'sensor spec instead \(--sensor PATH\)$')):
    estimate.estimate([noise], sources=['noise.bin'])
