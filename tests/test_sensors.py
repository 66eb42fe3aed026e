"""Any spinning LiDAR: sensor specs as data, sweeps of every preset written in
every point format and unfolded back to the simulator's own image, ring
assignment with and without a ring field on real sweeps, and specs
estimated from points against the manufacturers' tables."""

import dataclasses
import json
import os

import numpy as np
import pytest

from dusty_jax import configs, generator, models, runs, sensor as sensor_lib
from dusty_jax.data import estimate, points, prepare, simulated_lidar, unfolding
from dusty_jax.errors import DataError
from dusty_jax.sensor import PRESETS, SensorSpec

SAMPLES = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..', 'shared',
                       'data', 'sensors-sample')
OUSTER_PCAP = os.path.join(SAMPLES, 'OS-1-128_v2.3.0_1024x10_lb_n3.pcap')
OUSTER_JSON = os.path.join(SAMPLES, 'OS-1-128_v2.3.0_1024x10.json')


def sample(name):
  path = os.path.join(SAMPLES, name)
  if not os.path.isfile(path):
    pytest.skip(f'{path}: the real sensor samples are not beside the repository')
  return path


def ouster_sweep():
  sample(os.path.basename(OUSTER_PCAP))
  pytest.importorskip('ouster.sdk', reason="ouster-sdk is an optional extra")
  return points.read_points(OUSTER_PCAP)


# --- A sensor as data --------------------------------------------------------

def test_spec_file_round_trip_and_old_dicts(tmp_path):
  spec = dataclasses.replace(PRESETS['os1-64'], azimuth_offset_deg=tuple(np.linspace(-3, 3, 64)),
                             vertical_offset_m=tuple(np.linspace(-0.01, 0.01, 64)))
  path = str(tmp_path / 'lidar.json')
  sensor_lib.save(spec, path)
  assert sensor_lib.load(path) == spec
  assert sensor_lib.get_sensor(path) == spec
  # A dict saved before the offsets existed (runs' generator.json) still loads.
  old = PRESETS['kitti'].to_dict()
  del old['azimuth_offset_deg'], old['vertical_offset_m']
  assert SensorSpec.from_dict(old) == PRESETS['kitti']


@pytest.mark.parametrize('edit, message', [
    (lambda d: d.pop('width'), r"missing fields \['width'\]"),
    (lambda d: d.update(beams=3), r"unknown fields \['beams'\]"),
    (lambda d: d.update(elevation_deg=[1.0, 2.0]), 'must decrease strictly'),
    (lambda d: d.update(elevation_deg=[1.0, float('nan')]), 'finite'),
    (lambda d: d.update(vertical_offset_m=[0.0]), 'one finite value per ring'),
    (lambda d: d.update(native_width=100), 'width <= native_width'),
    (lambda d: d.update(width=12.5), 'width must be an integer'),
])
def test_a_bad_spec_file_is_one_error_naming_it(tmp_path, edit, message):
  d = PRESETS['vlp16'].to_dict()
  edit(d)
  path = tmp_path / 'bad.json'
  path.write_text(json.dumps(d))
  with pytest.raises(DataError, match=message) as e:
    sensor_lib.load(str(path))
  assert str(path) in str(e.value)
  path.write_text('{"name": ')
  with pytest.raises(DataError, match=f'{path}: not a JSON sensor spec'):
    sensor_lib.load(str(path))


def test_presets_follow_the_published_tables():
  vlp = PRESETS['vlp16']
  np.testing.assert_allclose(vlp.elevation_deg, np.arange(15, -16, -2))
  hdl32 = PRESETS['hdl32e']
  np.testing.assert_allclose(np.diff(hdl32.elevation_deg), -1.3333, atol=1e-3)
  hdl64 = PRESETS['hdl64e']
  assert hdl64.height == 64 and hdl64.elevation_deg[0] == 2.0
  assert abs(hdl64.elevation_deg[31] + 8.33) < 1e-9 and abs(hdl64.elevation_deg[32] + 8.83) < 1e-9
  for name, rings in (('os1-64', 64), ('os1-128', 128)):
    el = np.asarray(PRESETS[name].elevation_deg)
    assert len(el) == rings and el[0] == 22.5 and el[-1] == -22.5
  for spec in PRESETS.values():
    models.check_shape(spec)  # every preset fits the networks as it is


def test_a_width_the_network_cannot_take_names_the_nearest():
  with pytest.raises(ValueError, match=r'16x1010; the nearest valid width is 1008'):
    models.check_shape(PRESETS['vlp16'].with_width(1010))


def test_config_takes_a_spec_file_and_a_run_records_it(tmp_path):
  spec = dataclasses.replace(PRESETS['vlp16'], name='my-vlp', width=64)
  path = str(tmp_path / 'my.json')
  sensor_lib.save(spec, path)
  c = configs.default()
  c.sensor.file = path
  assert configs.validate(c) == spec  # the config's sensor, resolved once
  # As the trainer records it: the spec itself, in generator.json alone, so
  # the file may go.
  workdir = str(tmp_path / 'run')
  runs.record(workdir, c, spec, configs.model_settings(c), spec.nominal_angles())
  os.remove(path)
  assert generator.read_spec(workdir)[0] == spec
  saved = json.loads(open(os.path.join(workdir, configs.FILE)).read())
  assert saved['sensor'] == c.sensor.to_dict()  # the config as given
  assert configs.architecture_diff(configs.load(workdir), c) == {}
  c.sensor.file = path  # now missing
  with pytest.raises(configs.ConfigError, match=f'sensor.file=.*{path}: cannot read'):
    configs.validate(c)
  c.sensor.file = ''
  c.sensor.preset = 'vlp16'
  c.sensor.width = 1010
  with pytest.raises(configs.ConfigError, match='sensor.width=1010.*nearest valid width is 1008'):
    configs.validate(c)


# --- Simulated sweeps of every preset, in every format -----------------------

def _simulated_sweep(spec, seed=0):
  """The simulator's observed image and its points (one per return), with
  each point's row."""
  depth = np.asarray(simulated_lidar.render_arrays((seed, spec))[0], np.float64)
  hit = depth > 0
  xyz = (depth[..., None] * simulated_lidar.ray_directions(spec))[hit]
  return depth, xyz, np.nonzero(hit)[0]


RING_ORDERS = {
    'top_first': lambda rows, h: rows,
    'bottom_first': lambda rows, h: h - 1 - rows,
    # nuScenes' HDL-32E: ids in firing order, alternating upper and lower beams.
    'interleaved': lambda rows, h: np.argsort(np.r_[np.arange(0, h, 2), np.arange(1, h, 2)])[rows],
}
FORMATS = [('sweep.pcd', 'ascii'), ('sweep.pcd', 'binary'), ('sweep.pcd', 'binary_compressed'),
           ('sweep.ply', 'binary'), ('sweep.pcd.bin', None), ('sweep.npy', None)]


@pytest.mark.parametrize('name', sorted(set(PRESETS) - {'kitti', 'mpo'}) + ['kitti'])
def test_every_preset_unfolds_back_to_the_simulated_image(tmp_path, name):
  spec = PRESETS[name]
  depth, xyz, rows = _simulated_sweep(spec)
  for order, ids in RING_ORDERS.items():
    for fname, encoding in FORMATS:
      path = str(tmp_path / f'{order}_{fname}')
      fields = {'x': xyz[:, 0].astype(np.float32), 'y': xyz[:, 1].astype(np.float32),
                'z': xyz[:, 2].astype(np.float32), 'ring': ids(rows, spec.height).astype(np.uint16),
                'intensity': np.ones(len(xyz), np.float32)}
      points.write_points(path, fields, encoding=encoding)
      read = points.read_points(path)
      u = unfolding.unfold(read, spec, ring=points.ring_field(read, path), source=path)
      # float32 coordinates: depth equal to float32 rounding.
      same = np.isclose(u.depth, depth, rtol=1e-5, atol=1e-4) & ((u.depth > 0) == (depth > 0))
      assert same.mean() >= 0.999, (order, fname, same.mean(), u.summary())
      assert u.ring_rows is not None and sorted(u.ring_rows.values()) == sorted(set(rows))
  # No ring field (a KITTI .bin): rows by the nearest beam's elevation. The
  # simulator's points lie on their beams, so binning loses nothing here.
  path = str(tmp_path / 'sweep.bin')
  points.write_points(path, {'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2]})
  read = points.read_points(path)
  assert points.ring_field(read) is None
  u = unfolding.unfold(read, spec, source=path)
  same = np.isclose(u.depth, depth, rtol=1e-5, atol=1e-4) & ((u.depth > 0) == (depth > 0))
  assert same.mean() >= 0.999, (name, same.mean(), u.summary())


def test_placeholders_dual_returns_and_ranges_are_dropped_and_counted():
  spec = PRESETS['hdl32e']
  depth, xyz, rows = _simulated_sweep(spec, seed=1)
  n = len(xyz)
  origin = np.zeros((1600, 3))  # nuScenes' beams without a return
  farther = xyz[:500] * 1.5      # a second return behind the first
  beyond = xyz[500:600] / np.linalg.norm(xyz[500:600], axis=1, keepdims=True) * 150.0
  nan = np.full((7, 3), np.nan)
  all_xyz = np.concatenate([xyz, origin, farther, beyond, nan])
  ring = np.concatenate([rows, np.zeros(1600, int), rows[:500], rows[500:600], np.zeros(7, int)])
  u = unfolding.unfold(all_xyz, spec, ring=spec.height - 1 - ring)
  far_out = int(np.sum(np.linalg.norm(farther, axis=1) >= spec.max_depth))
  assert u.no_return == 1607
  assert u.out_of_range == 100 + far_out
  assert u.hidden == 500 - far_out  # second returns, behind the first
  assert u.placed == n and u.points == len(all_xyz)
  assert (u.no_return + u.out_of_range + u.off_elevation + u.between_columns + u.hidden
          + u.placed) == u.points
  # The nearer of two returns in a pixel is the one kept.
  np.testing.assert_allclose(u.depth, depth, rtol=1e-6)


def test_a_sweep_of_another_sensor_is_refused_in_one_line():
  spec = PRESETS['vlp16']
  az = np.linspace(-np.pi, np.pi, 5000)
  el = np.deg2rad(40.0)  # far above a VLP-16's +15 degrees
  xyz = 10 * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                       np.full_like(az, np.sin(el))], 1)
  with pytest.raises(DataError, match=r'sweep.pcd: 100% of its returns lie off the beams .* '
                     r'elevations span 40.0 to 40.0 degrees .* the spec\'s -15.0 to 15.0'):
    unfolding.unfold(xyz, spec, source='sweep.pcd')
  with pytest.raises(DataError, match='20 distinct ring ids, but sensor .vlp16. has 16 beams'):
    unfolding.unfold(xyz[:20], spec, ring=np.arange(20), source='x')


# --- Real sweeps ---------------------------------------------------------------

@pytest.mark.parametrize('name', ['vlp16_ring.pcd', 'pandar_xt16_channel.pcd'])
def test_real_16_beam_sweeps_rows_with_and_without_their_ring_field(name):
  path = sample(name)
  fields = points.read_points(path)
  ring = points.ring_field(fields, path)
  spec = PRESETS['vlp16']  # both have 16 beams 2 degrees apart from -15 to +15
  xyz = np.stack([fields[k] for k in 'xyz'], 1).astype(np.float64)
  r = np.linalg.norm(xyz, axis=1)
  with_ring = unfolding.unfold(fields, spec, ring=ring, source=path)
  # Each ring's rows from its measured elevation, whatever the driver's order.
  row_of_ring = np.array([with_ring.ring_rows[int(i)] for i in ring])
  row, inside = unfolding.nearest_beam(xyz[:, 2] / r, r, spec)
  assert np.mean(row == row_of_ring) >= 0.995
  without = unfolding.unfold(fields, spec, source=path)
  assert np.mean(with_ring.depth == without.depth) >= 0.995


def test_real_ouster_sweep_rows_from_its_own_calibration():
  fields = ouster_sweep()
  ring = points.ring_field(fields)
  unit = sensor_lib.from_ouster_metadata(OUSTER_JSON)
  assert unit.height == 128 and unit.native_width == 1024
  xyz = np.stack([fields[k] for k in 'xyz'], 1).astype(np.float64)
  r = np.linalg.norm(xyz, axis=1)
  row, _ = unfolding.nearest_beam(xyz[:, 2] / r, r, unit)
  assert np.mean(row == ring) >= 0.98  # measured 100.00%
  # Without the beam-origin offsets the nearest points drift off their beam
  # (10 of 107,647 here: the lidar frame's origin is 16 mm from the beams').
  bare = dataclasses.replace(unit, vertical_offset_m=())
  row_bare, _ = unfolding.nearest_beam(xyz[:, 2] / r, r, bare)
  assert np.mean(row_bare == ring) < np.mean(row == ring)
  a = unfolding.unfold(fields, unit, ring=ring)
  b = unfolding.unfold(fields, unit)
  assert a.ring_rows == {j: j for j in range(128)}  # beam 0 is the top beam
  assert np.mean(a.depth == b.depth) >= 0.98
  # With its azimuth offsets each firing has a pixel of its own.
  assert a.hidden == 0 and a.placed == a.points - a.no_return - a.out_of_range


def test_estimated_specs_match_the_published_tables():
  vlp = estimate.estimate([points.read_points(sample('vlp16_ring.pcd'))], name='vlp')
  assert vlp.spec.height == 16  # every ring: the one without a return inferred
  assert vlp.beams_inferred == [15] and vlp.beams_measured == 15
  err = np.abs(np.asarray(vlp.spec.elevation_deg) - PRESETS['vlp16'].elevation_deg)
  assert err.mean() <= 0.05 and err[:15].max() < 1e-3
  # Without its ring field: the 15 beams that returned (the lowest of them
  # has all its returns within 1 m, where no far point votes for it).
  bare = estimate.estimate([{k: v for k, v in points.read_points(
      sample('vlp16_ring.pcd')).items() if k != 'ring'}])
  np.testing.assert_allclose(bare.spec.elevation_deg, PRESETS['vlp16'].elevation_deg[:15],
                             atol=1e-3)
  # PandarXT16 (Hesai's manual: -15 to +15 degrees, 2 apart), without its field.
  xt = points.read_points(sample('pandar_xt16_channel.pcd'))
  fit = estimate.estimate([{k: v for k, v in xt.items() if k != 'channel'}])
  assert fit.spec.height == 16
  assert np.abs(np.asarray(fit.spec.elevation_deg) - PRESETS['vlp16'].elevation_deg).mean() <= 0.05
  assert 'rows' not in fit.summary().split('fit:')[0]


def test_estimated_ouster_spec_matches_its_metadata():
  fields = ouster_sweep()
  unit = sensor_lib.from_ouster_metadata(OUSTER_JSON)
  for given in (fields, {k: v for k, v in fields.items() if k != 'ring'}):
    fit = estimate.estimate([given])
    assert fit.spec.height == 128 and fit.firings == 1024
    assert np.abs(np.asarray(fit.spec.elevation_deg) - unit.elevation_deg).mean() <= 0.05
    np.testing.assert_allclose(fit.spec.vertical_offset_m, unit.vertical_offset_m, atol=1e-3)
    assert fit.agreement >= 0.98


# --- Preparing a folder of any sensor's files --------------------------------

def test_prepare_a_folder_of_files_with_a_preset_and_estimated(tmp_path):
  spec = PRESETS['vlp16'].with_width(256)
  root = tmp_path / 'raw'
  images = {}
  for i, (fname, enc) in enumerate(FORMATS * 2):
    depth, xyz, rows = _simulated_sweep(spec, seed=i)
    path = str(root / f'{i:03d}_{fname}')
    points.write_points(path, {'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2],
                               'ring': (spec.height - 1 - rows).astype(np.uint16)},
                        encoding=enc)
    images[path] = depth
  out = str(tmp_path / 'prepared')
  meta = prepare.prepare('files', str(root), out, spec, log=lambda m: None)
  assert sum(meta['splits'].values()) == 12 and meta['splits']['train'] == 10
  assert sensor_lib.load(os.path.join(out, prepare.SENSOR_FILE)) == spec
  train = np.load(os.path.join(out, 'train.npy'))
  listed = prepare.Files().list_split(str(root), 'train')
  for path, scan in zip(listed, train):
    same = np.isclose(scan, images[path], rtol=1e-5, atol=1e-4)
    assert same.mean() >= 0.999
  # Split lists decide where given; --sensor auto estimates and writes a spec.
  (root / 'train.txt').write_text('\n'.join(os.path.basename(p) for p in sorted(images)[:8]))
  (root / 'test.txt').write_text(os.path.basename(sorted(images)[8]))
  logs = []
  meta = prepare.prepare('files', str(root), out, auto_sensor=True, log=logs.append)
  assert meta['splits'] == {'train': 8, 'val': 0, 'test': 1}
  estimated = sensor_lib.load(os.path.join(out, prepare.SENSOR_FILE))
  np.testing.assert_allclose(estimated.elevation_deg, spec.elevation_deg, atol=1e-3)
  assert any('estimated sensor' in m for m in logs)
  with pytest.raises(DataError, match='needs --sensor'):
    prepare.prepare('files', str(root), out, None)


# --- Training follows the spec --------------------------------------------------

# 128 rings here; 16 rings: test_readme's own-lidar commands train on
# simulated scans of a 16-beam spec file; 64: every other training test; 32:
# the networks' shapes below.
@pytest.mark.slow
@pytest.mark.parametrize('preset', ['os1-128'])
def test_smoke_training_and_evaluation_on_simulated_scans_of_a_preset(tmp_path, preset):
  from dusty_jax import trainer
  from train_helpers import tiny_config
  config = tiny_config(num_steps=2, checkpoint_every=2, log_every=1, image_every=2)
  config.sensor.update(preset=preset, height=0, width=64)
  config.data.cache = str(tmp_path / 'cache')
  config.data.num_synthetic = 40
  config.final_eval.update(num_synthesis=4, points=64)
  workdir = str(tmp_path / 'run')
  trainer.train_and_evaluate(config, workdir, log=lambda m: None)
  spec = sensor_lib.from_config(config.sensor)
  assert spec.height == PRESETS[preset].height and spec.width == 64
  with open(os.path.join(workdir, 'final_evaluation.json')) as f:
    result = json.load(f)
  flat = json.dumps(result)
  assert 'NaN' not in flat and 'Infinity' not in flat
  assert generator.read_spec(workdir)[0] == spec  # the run's record of its sensor


@pytest.mark.parametrize('rings, width', [(16, 256), (32, 1024), (64, 2048), (128, 2048)])
def test_the_networks_take_16_to_128_rings_and_256_to_2048_columns(rings, width):
  """Shapes only (jax.eval_shape: traced, not run): the generator makes the
  sensor's (H, W) and the discriminator one logit per scan."""
  import jax
  import jax.numpy as jnp
  spec = dataclasses.replace(PRESETS['os1-128'], name=f'r{rings}',
                             elevation_deg=tuple(np.linspace(20, -20, rings)),
                             width=width, native_width=2048)
  settings = models.ModelSettings(model='dusty1', latent_dim=16, ch_base=4, ch_max=16)
  g, d = settings.generator(spec), settings.discriminator(spec)
  z = jax.ShapeDtypeStruct((2, 16), jnp.float32)
  g_vars = jax.eval_shape(lambda z: g.init(jax.random.key(0), z), z)
  out = jax.eval_shape(lambda v, z: g.apply(v, z), g_vars, z)
  assert out.shape[:3] == (2, rings, width)
  x = jax.ShapeDtypeStruct((2, rings, width), jnp.float32)
  d_vars = jax.eval_shape(lambda x: d.init(jax.random.key(0), x), x)
  assert jax.eval_shape(lambda v, x: d.apply(v, x), d_vars, x).shape == (2,)
