"""The peers' datasets (data/kitti360.py, data/nuscenes.py): trees laid out as
distributed, with a few sweeps of known depth, prepared into the peers' splits
at their image sizes."""

import json
import os

import numpy as np
import pytest

from conftest import random_depth
from dusty_jax.data import arrays, kitti as kitti_io, kitti360, nuscenes, prepare
from dusty_jax.data import simulated_lidar, write_points
from dusty_jax.errors import DataError
from dusty_jax.sensor import get_sensor
from dusty_jax.tools import prepare as prepare_tool

QUIET = dict(log=lambda m: None)


# --- KITTI-360 ---------------------------------------------------------------------------

def kitti360_tree(root, drives=((3, 2), (4, 1), (0, 1), (2, 1), (8, 1))):
  """ROOT/data_3d_raw/2013_05_28_drive_NNNN_sync/velodyne_points/data/*.bin in
  sensor order; returns {path: depth}."""
  hdl64e = get_sensor(kitti360.SENSOR)
  truth = {}
  for drive, n in drives:
    for i in range(n):
      depth = random_depth(hdl64e, seed=100 * drive + i)
      path = os.path.join(root, 'data_3d_raw', f'2013_05_28_drive_{drive:04d}_sync',
                          'velodyne_points', 'data', f'{i:010d}.bin')
      kitti_io.write_bin(path, simulated_lidar.to_sensor_order(depth, hdl64e))
      truth[path] = depth
  return truth


def test_kitti360_prepares_the_lidargen_split_at_64x1024(tmp_path):
  root, out = str(tmp_path / 'KITTI-360'), str(tmp_path / 'out')
  truth = kitti360_tree(root)
  meta = prepare.prepare('kitti360', root, out, **QUIET)
  assert meta['splits'] == {'train': 3, 'val': 0, 'test': 2}  # drive 8 is in neither
  assert meta['shape'] == [64, 1024] and meta['sensor'] == 'hdl64e'
  hdl64e = get_sensor('hdl64e')
  for split, drives in (('train', ('0003', '0004')), ('test', ('0000', '0002'))):
    got = arrays.load_split(out, split, hdl64e)
    want = [truth[p] for p in sorted(truth) if any(f'drive_{d}_' in p for d in drives)]
    assert got.shape == (len(want), 64, 1024)
    np.testing.assert_allclose(np.asarray(got), np.stack(want), rtol=1e-5)
  assert not os.path.exists(arrays.split_path(out, 'val'))


def test_kitti360_root_may_be_data_3d_raw_and_a_wrong_root_is_one_line(tmp_path, capsys):
  root = tmp_path / 'KITTI-360'
  kitti360_tree(str(root), drives=((3, 1), (0, 1)))
  raw = str(root / 'data_3d_raw')
  assert kitti360.list_split(raw, 'train') == kitti360.list_split(str(root), 'train')
  assert len(kitti360.list_split(raw, 'train')) == 1
  out = str(tmp_path / 'out')
  prepare_tool.main(['--dataset', 'kitti360', '--root', raw, '--out', out])
  text = capsys.readouterr().out
  assert 'train: 1 scans written' in text and 'test: 1 scans written' in text
  with pytest.raises(SystemExit, match=r'data_3d_raw: no such directory; expected the '
                     r'KITTI-360 layout ROOT/data_3d_raw/2013_05_28_drive_NNNN_sync/'
                     r'velodyne_points/data/\*\.bin'):
    prepare_tool.main(['--dataset', 'kitti360', '--root', str(tmp_path), '--out', out])
  with pytest.raises(SystemExit, match='topic and every are for recordings'):
    prepare_tool.main(['--dataset', 'kitti360', '--root', raw, '--out', out, '--every', '2'])


# --- nuScenes ----------------------------------------------------------------------------

def lidar_top_sweep(depth, sensor, placeholders=300, seed=0):
  """A LIDAR_TOP sweep of a depth image: x, y, z, intensity, ring (ring 0
  the bottom beam), and points at the origin for beams without a return,
  as nuScenes keeps them."""
  rng = np.random.default_rng(seed)
  keep = depth > 0
  xyz = (depth[..., None] * simulated_lidar.ray_directions(sensor))[keep]
  ring = np.broadcast_to(np.arange(sensor.height)[::-1, None], depth.shape)[keep]
  ring = np.concatenate([ring, rng.integers(0, sensor.height, placeholders)])
  xyz = np.concatenate([xyz, np.zeros((placeholders, 3))])
  return {'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2],
          'intensity': rng.uniform(0, 255, len(xyz)), 'ring': ring}


def _record(filename, key_frame, timestamp):
  """A sample_data record as nuScenes writes them (the fields read here and
  a few beside them)."""
  return {'token': f't{timestamp}', 'sample_token': 's0', 'ego_pose_token': 'e0',
          'calibrated_sensor_token': 'c0', 'timestamp': timestamp, 'fileformat':
          filename.rsplit('.', 1)[-1], 'is_key_frame': key_frame, 'height': 0, 'width': 0,
          'filename': filename, 'prev': '', 'next': ''}


def nuscenes_tree(root, versions=(('v1.0-trainval', 2), ('v1.0-test', 1))):
  """ROOT/VERSION/sample_data.json listing LIDAR_TOP sweeps (written under
  ROOT/sweeps/LIDAR_TOP), a key frame and a camera image each; returns
  {version: [depth of each sweep, in file name order]}."""
  hdl32e = get_sensor(nuscenes.SENSOR)
  truth, stamp = {}, 1_532_402_927_000_000
  for v, (version, n) in enumerate(versions):
    records, truth[version] = [], []
    for i in range(n + 1):
      stamp += 50_000
      depth = random_depth(hdl32e, seed=10 * v + i)
      key_frame = i == n  # the last one: a key frame, which the peers leave out
      name = (f'{"samples" if key_frame else "sweeps"}/LIDAR_TOP/'
              f'n008-2018-08-01-15-16-36-0400__LIDAR_TOP__{stamp}.pcd.bin')
      write_points(os.path.join(root, name), lidar_top_sweep(depth, hdl32e, seed=i))
      records.append(_record(name, key_frame, stamp))
      records.append(_record(f'sweeps/CAM_FRONT/n008__CAM_FRONT__{stamp}.jpg', False, stamp))
      if not key_frame:
        truth[version].append(depth)
    os.makedirs(os.path.join(root, version))
    with open(os.path.join(root, version, nuscenes.TABLE), 'w') as f:
      json.dump(records[::-1], f)  # the table's order is not the files'
  return truth


def test_nuscenes_prepares_the_version_split_at_32x1024(tmp_path):
  root, out = str(tmp_path / 'nuscenes'), str(tmp_path / 'out')
  truth = nuscenes_tree(root)
  logs = []
  meta = prepare.prepare('nuscenes', root, out, log=logs.append)
  assert meta['splits'] == {'train': 2, 'val': 0, 'test': 1}
  assert meta['shape'] == [32, 1024] and meta['sensor'] == 'hdl32e'
  assert 'val: no files found, split not written' in logs
  hdl32e = get_sensor('hdl32e')
  for split, version in (('train', 'v1.0-trainval'), ('test', 'v1.0-test')):
    got = arrays.load_split(out, split, hdl32e)
    assert got.shape == (len(truth[version]), 32, 1024)
    # Rows from the ring field, the placeholders at the origin dropped.
    np.testing.assert_allclose(np.asarray(got), np.stack(truth[version]), rtol=1e-5)


def test_nuscenes_mini_alone_is_the_training_split(tmp_path, capsys):
  root, out = str(tmp_path / 'nuscenes'), str(tmp_path / 'out')
  truth = nuscenes_tree(root, versions=(('v1.0-mini', 3),))
  prepare_tool.main(['--dataset', 'nuscenes', '--root', root, '--out', out])
  text = capsys.readouterr().out
  assert 'train: 3 scans written' in text and 'test: no files found' in text
  got = arrays.load_split(out, 'train', get_sensor('hdl32e'))
  np.testing.assert_allclose(np.asarray(got), np.stack(truth['v1.0-mini']), rtol=1e-5)


def test_nuscenes_tree_faults_are_one_line_naming_the_table(tmp_path):
  root = tmp_path / 'nuscenes'
  with pytest.raises(FileNotFoundError, match=(
      r'nuscenes: no sample_data\.json in any of v1\.0-trainval, v1\.0-test, v1\.0-mini; '
      r'expected the nuScenes layout ROOT/VERSION/sample_data\.json')):
    nuscenes.list_split(str(root), 'train')
  nuscenes_tree(str(root), versions=(('v1.0-trainval', 3),))
  table = root / 'v1.0-trainval' / nuscenes.TABLE
  gone = sorted((root / 'sweeps' / 'LIDAR_TOP').iterdir())[1]
  gone.unlink()
  out = tmp_path / 'out'
  with pytest.raises(DataError, match=(
      rf'^{table}: 1 of its 3 LIDAR_TOP sweeps are not under {root}, e\.g\. {gone}; '
      r'download every part of v1\.0-trainval, or prepare the files there are with '
      r'--dataset files$')):
    prepare.prepare('nuscenes', str(root), str(out), **QUIET)
  assert not out.exists()
  for content in ('{"not": "a list"}', '[{"token": "no filename"}]', '[{"filename": '):
    table.write_text(content)
    with pytest.raises(DataError, match=rf'^{table}: not a (readable )?nuScenes'):
      nuscenes.list_split(str(root), 'train')


def test_the_prepare_tool_knows_the_peers_datasets():
  assert {'kitti360', 'nuscenes'} <= set(prepare.READERS)
  for name, size in (('kitti360', (64, 1024)), ('nuscenes', (32, 1024))):
    assert get_sensor(prepare.DATASET_SENSOR[name]).shape == size
