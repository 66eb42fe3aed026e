"""restore(): the classical fills on hand-made scans, the scores, and the
contract of every input."""

import json

import jax
import numpy as np
import pytest

import dusty_jax
from dusty_jax import codec, corrupt, errors, evaluation, interpolation, restoration
from dusty_jax.data import simulated_lidar
from dusty_jax.metrics import restoration as fill_metrics

H, W = 64, 256
LO, HI = 0.9, 120.0


@pytest.fixture(scope='module')
def params():
  return dusty_jax.load_pretrained('sim-dusty1')


def plane(rows=H, cols=W):
  """Depth whose inverse is linear in (row, column) across the middle
  columns: what linear interpolation must restore exactly there."""
  r, c = np.mgrid[:rows, :cols]
  return 1.0 / (0.02 + 0.001 * r + 0.0002 * np.abs(c - cols / 2))


def test_linear_restores_a_plane_between_kept_beams():
  depth = plane()
  known = np.zeros((H, W), bool)
  known[::4] = True
  out = interpolation.linear(np.where(known, depth, 0.0), known, LO, HI)
  inside = slice(0, 61), slice(8, W - 8)  # below row 60 no beam; |c - W/2| bends at W/2
  fold = slice(0, 61), slice(W // 2 - 1, W // 2 + 2)
  err = np.abs(out - depth) / depth
  err[fold] = 0
  assert err[inside].max() < 1e-5


def test_linear_crosses_the_seam():
  # Known columns 4, 12, ..., 252: column 0 lies halfway between 252 and 4
  # (260) across the seam.
  depth = np.tile(np.linspace(5.0, 80.0, W), (H, 1))
  known = np.zeros((H, W), bool)
  known[:, 4::8] = True
  out = interpolation.linear(np.where(known, depth, 0.0), known, LO, HI)
  want = 1.0 / (0.5 / depth[0, 252] + 0.5 / depth[0, 4])
  np.testing.assert_allclose(out[10:50, 0], want, rtol=1e-5)


def test_nearest_takes_a_known_value_and_linear_stays_between():
  rng = np.random.default_rng(0)
  depth = np.where(np.arange(W) < W // 2, 10.0, 50.0) * np.ones((H, 1))  # a step edge
  known = rng.uniform(size=(H, W)) < 0.2
  given = np.where(known, depth, 0.0)
  near = interpolation.nearest(given, known, LO, HI)
  assert set(np.unique(near)) <= {10.0, 50.0}
  lin = interpolation.linear(given, known, LO, HI)
  assert lin.min() >= 10.0 - 1e-4 and lin.max() <= 50.0 + 1e-3
  # Away from the edges (and the seam, where 50 m meets 10 m) both are exact.
  away = (np.abs(np.arange(W) - W // 2) > 20) & (np.arange(W) > 20) & (np.arange(W) < W - 20)
  np.testing.assert_allclose(lin[:, away], depth[:, away], rtol=1e-5)
  np.testing.assert_allclose(near[:, away], depth[:, away])


def test_morphological_fills_every_pixel_and_keeps_a_constant_scene():
  known = np.zeros((H, W), bool)
  known[::4] = True
  out = interpolation.morphological(np.where(known, 20.0, 0.0), known, LO, HI)
  np.testing.assert_allclose(out, 20.0, rtol=1e-5)
  rng = np.random.default_rng(1)
  depth = rng.uniform(2, 100, (H, W))
  known = rng.uniform(size=(H, W)) < 0.1
  out = interpolation.morphological(np.where(known, depth, 0.0), known, LO, HI)
  assert np.isfinite(out).all() and out.min() >= LO and out.max() <= HI


def test_directional_finds_the_nearest_return_each_way():
  depth = np.zeros((4, 6))
  depth[1, 4] = 7.0
  known = depth > 0
  up, d_up = interpolation.directional(depth, known, LO, HI, 'up')
  assert up[3, 4] == 7.0 and d_up[3, 4] == 2 and np.isnan(up[0, 4])
  right, d_right = interpolation.directional(depth, known, LO, HI, 'right')
  assert right[1, 5] == 7.0 and d_right[1, 5] == 5  # 5 -> 0 -> ... -> 4, wrapped
  left, d_left = interpolation.directional(depth, known, LO, HI, 'left')
  assert left[1, 0] == 7.0 and d_left[1, 0] == 2  # 0 -> 5 -> 4, wrapped


def test_scores_against_a_known_error():
  sensor = dusty_jax.get_sensor('kitti')
  angles = sensor.nominal_angles()
  clean = np.full((1, H, W), 10.0, np.float32)
  clean[0, :, W // 2:] = 40.0  # an edge at W/2 (and at the seam)
  known = np.zeros((1, H, W), bool)
  known[0, ::2] = True
  exact = fill_metrics.scores(clean, clean, known, angles, sensor)
  assert exact['abs_rel'][0] == 0 and exact['cd'][0] < 1e-12
  off = clean * 1.1
  s = fill_metrics.scores(off, clean, known, angles, sensor)
  np.testing.assert_allclose(s['abs_rel'][0], 0.1, rtol=1e-5)
  np.testing.assert_allclose(s['edge_abs_rel'][0], 0.1, rtol=1e-5)
  half = np.where(known, clean, off)  # kept pixels exact: Table III's pixels halve it
  np.testing.assert_allclose(fill_metrics.scores(half, clean, known, angles, sensor)
                             ['scan_abs_rel'][0], 0.05, rtol=1e-5)
  want_mae = 0.1 * (10 + 40) / 2
  np.testing.assert_allclose(s['mae'][0], want_mae, rtol=1e-4)
  edges = fill_metrics.edges(clean[0], sensor)
  assert edges[:, [0, W // 2 - 1, W // 2, W - 1]].all() and edges.sum() == 4 * H


def test_corruption_known_matches_what_the_corruption_removes(params):
  depth = np.asarray(simulated_lidar.render_scan(3, params.sensor).depth)[None]
  clean = codec.encode(np.repeat(depth, 3, 0), params.sensor)
  k_corrupt = jax.random.split(jax.random.key(0))[0]
  for spec in ('drop:0.9', 'beams:4'):
    known = evaluation.corruption_known(spec, 3, params.sensor.shape)
    for i in range(3):
      bad = np.asarray(corrupt.apply(spec, jax.random.fold_in(k_corrupt, i), clean[i],
                                     params.sensor))
      was = np.asarray(clean[i]) > codec.ALPHA
      np.testing.assert_array_equal(bad > codec.ALPHA, was & known[i])


def test_restore_keeps_known_returns_and_fills_the_rest(params):
  depth = np.asarray(simulated_lidar.render_scan(5, params.sensor).depth)
  known = np.zeros(depth.shape, bool)
  known[::4] = True
  given = np.where(known, depth, 0.0)
  for method in ('nearest', 'linear', 'morphological', 'auto'):
    out = restoration.restore(params, given, known, method=method)
    assert out['depth'].shape == depth.shape and out['method'] in restoration.METHODS
    assert out['method'] != 'auto'
    returns = known & (depth > 0)
    np.testing.assert_array_equal(out['depth'][returns], depth[returns])
    assert (out['depth'] > 0).all()
  batch = restoration.restore(params, np.stack([given, given]), np.stack([known, known]),
                              method='linear')
  np.testing.assert_array_equal(batch['depth'][1], out['depth'] if out['method'] == 'linear'
                                else batch['depth'][0])


@pytest.mark.slow  # compiles the inversion's search
def test_restore_by_inversion_gives_measurability_and_a_scan(params):
  depth = np.asarray(simulated_lidar.render_scan(6, params.sensor).depth)
  known = np.random.default_rng(0).uniform(size=depth.shape) > 0.5
  out = restoration.restore(params, np.where(known, depth, 0.0), known, method='inversion',
                            num_steps=2)
  assert out['measurability'].shape == depth.shape
  assert 0 <= out['measurability'].min() and out['measurability'].max() <= 1
  np.testing.assert_array_equal(out['scan'][known], np.where(known, depth, 0.0)[known])
  assert np.isfinite(out['depth']).all()


@pytest.mark.parametrize('case, match', [
    ('shape', r'does not match the model\'s sensor'),
    ('nan', r'depth: 1 of .* NaN'),
    ('negative', r'negative'),
    ('no_return', r'no known return'),
    ('known_shape', r'known of shape'),
    ('known_dtype', r'expected bool'),
])
def test_restore_refuses_bad_input_in_one_line(params, case, match):
  depth = np.full(params.sensor.shape, 20.0, np.float32)
  known = None
  if case == 'shape':
    depth = np.full((32, 256), 20.0, np.float32)
  elif case == 'nan':
    depth[3, 4] = np.nan
  elif case == 'negative':
    depth[3, 4] = -1
  elif case == 'no_return':
    known = np.zeros(depth.shape, bool)
  elif case == 'known_shape':
    known = np.ones((2,) + depth.shape, bool)
  else:
    known = np.ones(depth.shape, np.float32)
  with pytest.raises(errors.InputError, match=match) as e:
    restoration.restore(params, depth, known, method='linear')
  assert '\n' not in str(e.value)


def test_restore_names_the_methods(params):
  with pytest.raises(ValueError, match='known methods'):
    restoration.restore(params, np.full(params.sensor.shape, 9.0), method='cubic')


def test_restore_is_public():
  assert dusty_jax.restore is restoration.restore


def test_on_grid_places_each_beam_on_the_row_nearest_in_elevation():
  target = dusty_jax.get_sensor('kitti')
  source = dusty_jax.get_sensor('vlp16').with_width(target.width)
  scan = np.arange(16, dtype=np.float32)[:, None] + np.ones((16, target.width), np.float32)
  depth, known = restoration.on_grid(scan, source, target)
  rows = np.flatnonzero(known.any(axis=1))
  assert known[rows].all() and depth.shape == target.shape
  # The VLP-16's beams at +1 .. -15 degrees lie in the HDL-64E's +2 .. -24.9.
  in_view = [i for i, e in enumerate(source.elevation_deg) if -15.5 < e < 1.5]
  assert len(rows) == len(in_view) == 8 + 1
  for i in in_view:
    j = np.abs(np.asarray(target.elevation_deg) - source.elevation_deg[i]).argmin()
    np.testing.assert_array_equal(depth[j], scan[i])
  with pytest.raises(errors.InputError, match=r"at 'kitti''s width"):
    restoration.on_grid(scan[:, :100], source, target)


def test_restore_cli_scores_each_method_beside_linear(tmp_path, capsys, params):
  from dusty_jax.tools import restore as restore_tool
  depth = np.stack([simulated_lidar.render_scan(s, params.sensor).depth for s in (1, 2)])
  np.save(tmp_path / 'scans.npy', depth)
  out = tmp_path / 'out'
  restore_tool.main(['--workdir', 'sim-dusty1', '--input', str(tmp_path / 'scans.npy'),
                     '--corrupt', 'beams:4', '--methods', 'nearest', '--out', str(out)])
  m = json.load(open(out / 'metrics.json'))
  assert set(m['mean']) == {'nearest', 'linear'} and m['num'] == 2
  known = evaluation.corruption_known('beams:4', 2, params.sensor.shape)
  for i, name in enumerate(('scans_00000', 'scans_00001')):
    filled = np.load(out / f'{name}_nearest_depth.npy')
    direct = restoration.restore(params, np.where(known[i], depth[i], 0.0), known[i],
                                 method='nearest')['depth']
    np.testing.assert_array_equal(filled, direct)
    assert (out / f'{name}.png').is_file() and (out / f'{name}_linear.ply').is_file()
  want = fill_metrics.scores(np.stack([np.load(out / f'scans_0000{i}_linear_depth.npy')
                                       for i in range(2)]), depth, known, params.angles,
                             params.sensor)
  assert m['mean']['linear']['abs_rel'] == pytest.approx(float(np.mean(want['abs_rel'])))
  assert 'x linear' in capsys.readouterr().out


@pytest.mark.slow  # compiles the inversion's search
def test_the_invert_tool_shows_linear_beside_inversion(params):
  depth = np.stack([simulated_lidar.render_scan(s, params.sensor).depth for s in (3, 4)])
  rec = evaluation.restoration(params, depth, corruption='drop:0.9', num_steps=2)
  fill = rec['fill']
  lin = evaluation.fill(params, depth, corruption='drop:0.9', method='linear')
  assert fill['linear'] == lin['mean']
  assert fill['inversion']['abs_rel'] > 0 and fill['inversion']['edge_abs_rel'] > 0
  lines = evaluation.fill_lines(fill)
  assert 'linear interpolation' in lines[2] and 'inversion / linear AbsRel' in lines[3]
  assert 'fill' not in evaluation.restoration(params, depth[:1], num_steps=1)


def test_auto_is_the_shipped_learned_fill_and_beats_linear_on_a_held_out_scene(params):
  """The shipped restorer fills a scan of a scene no training used better
  than linear interpolation (beams:4; the benchmark measures it on 32)."""
  assert restoration.auto_method(params) == 'learned'
  depth = np.stack([simulated_lidar.render_scan(s, params.sensor).depth for s in (9001, 9002)])
  known = evaluation.corruption_known('beams:4', 2, params.sensor.shape)
  given = np.where(known, depth, 0.0)
  auto = restoration.restore(params, given, known)
  assert auto['method'] == 'learned'
  lin = restoration.restore(params, given, known, method='linear')
  s_auto = fill_metrics.scores(auto['depth'], depth, known, params.angles, params.sensor)
  s_lin = fill_metrics.scores(lin['depth'], depth, known, params.angles, params.sensor)
  assert np.mean(s_auto['abs_rel']) < np.mean(s_lin['abs_rel'])


def test_a_sensor_without_a_restorer_falls_back_to_linear(params):
  other = params.replace(sensor=params.sensor.with_width(128),
                         angles=params.sensor.with_width(128).nominal_angles())
  assert restoration.auto_method(other) == 'linear'
  with pytest.raises(errors.InputError, match="no restorer ships for sensor 'kitti'"):
    restoration.restore(other, np.full((64, 128), 9.0), method='learned')
