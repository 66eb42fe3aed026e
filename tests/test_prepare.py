"""Readers and the prepare CLI on small folders written in the real layouts."""

import os
import shutil

import numpy as np
import pytest

from conftest import random_depth, sensor_order_points
from dusty_jax.data import arrays, kitti as kitti_io
from dusty_jax.data import prepare
from dusty_jax.sensor import get_sensor
from dusty_jax.tools import prepare as prepare_tool


def _kitti_tree(root, kitti, seqs=(('00', 3), ('08', 2), ('11', 1))):
  truth = {}
  for seq, n in seqs:
    for i in range(n):
      d = random_depth(kitti, seed=int(seq) * 10 + i)
      path = os.path.join(root, 'sequences', seq, 'velodyne', f'{i:06d}.bin')
      kitti_io.write_bin(path, sensor_order_points(d, kitti, seed=i))
      truth[path] = d
  return truth


def test_prepare_kitti_layout(kitti, tmp_path):
  root, out = str(tmp_path / 'kitti'), str(tmp_path / 'prepared')
  truth = _kitti_tree(root, kitti)
  # A truncated file and an empty one in the training split.
  bad = os.path.join(root, 'sequences', '00', 'velodyne', '000099.bin')
  with open(bad, 'wb') as f:
    f.write(b'\0' * 20)
  open(os.path.join(root, 'sequences', '01_empty.bin'), 'wb').close()
  empty = os.path.join(root, 'sequences', '01', 'velodyne', '000000.bin')
  os.makedirs(os.path.dirname(empty))
  open(empty, 'wb').close()
  logs = []
  meta = prepare.prepare('kitti', root, out, log=logs.append)
  assert meta['splits'] == {'train': 3, 'val': 2, 'test': 1}
  reasons = {s['path']: s['reason'] for s in meta['skipped']['train']}
  assert 'not a multiple of 16' in reasons[bad]
  assert 'empty file' in reasons[empty]
  assert any('skipped' in l and bad in l for l in logs)
  train = arrays.load_split(out, 'train', kitti)
  assert train.dtype == np.float32 and train.shape == (3, 64, 256)
  assert isinstance(train, np.memmap)
  want = [truth[p] for p in sorted(truth) if '/00/' in p]
  np.testing.assert_allclose(np.asarray(train), np.stack(want), rtol=1e-5)
  angles = arrays.load_angles(out, kitti)
  assert angles.shape == (2, 64, 256) and np.isfinite(angles).all()
  # Estimated angles agree with the nominal angles the test wrote.
  nominal = kitti.nominal_angles()
  np.testing.assert_allclose(angles[0], nominal[0], atol=1e-5)


def test_prepare_cli_and_errors(kitti, tmp_path, capsys):
  root, out = str(tmp_path / 'kitti'), str(tmp_path / 'out')
  _kitti_tree(root, kitti, seqs=(('00', 1),))
  prepare_tool.main(['--dataset', 'kitti', '--root', root, '--out', out])
  assert 'train: 1 scans written' in capsys.readouterr().out
  with pytest.raises(SystemExit, match=(r'--dataset=nuscene: value should be one of '
                                       r'<files\|kitti\|kitti360\|mpo\|nuscenes>')):
    prepare_tool.main(['--dataset', 'nuscene', '--root', root, '--out', out])
  with pytest.raises(SystemExit, match='no such directory'):
    prepare_tool.main(['--dataset', 'kitti', '--root', str(tmp_path / 'nope'),
                       '--out', out])
  with pytest.raises(SystemExit, match='sequences: no such directory'):
    prepare_tool.main(['--dataset', 'kitti', '--root', str(tmp_path), '--out', out])


def test_read_bin_rejects_nan(tmp_path):
  path = str(tmp_path / 'nan.bin')
  np.float32([[1, 2, 3, 0], [np.nan, 1, 1, 0]]).tofile(path)
  with pytest.raises(ValueError, match=r'nan\.bin: 1 of 2 points have NaN'):
    kitti_io.read_bin(path)


def test_prepare_mpo_layout(tmp_path):
  mpo = get_sensor('mpo')
  data = tmp_path / 'mpo' / 'Data'
  data.mkdir(parents=True)
  depth = random_depth(mpo, seed=11)
  pts = sensor_order_points(depth, mpo, extra_offgrid=False)[:, :3]
  el = np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1]))
  ring = mpo.height - 1 - np.argmin(np.abs(el[:, None] - mpo.elevation), 1)
  np.save(data / 'class0_set001_scan00001.npy',
          np.concatenate([pts, ring[:, None].astype(np.float32)], 1))
  np.save(data / 'class0_set007_scan00002.npy', np.zeros((4, 2), np.float32))
  meta = prepare.prepare('mpo', str(tmp_path / 'mpo'), str(tmp_path / 'out'))
  assert meta['splits']['train'] == 1 and meta['splits']['val'] == 0
  assert 'needs x, y, z and a ring id' in meta['skipped']['val'][0]['reason']
  got = arrays.load_split(str(tmp_path / 'out'), 'train', mpo)
  np.testing.assert_allclose(got[0], depth, rtol=1e-5)


def test_load_split_shape_mismatch(tmp_path, kitti):
  np.save(tmp_path / 'train.npy', np.zeros((2, 32, 256), np.float32))
  with pytest.raises(ValueError, match=r'train\.npy: array of shape'):
    arrays.load_split(str(tmp_path), 'train', kitti)
  with pytest.raises(FileNotFoundError, match='dusty_jax.tools.prepare'):
    arrays.load_split(str(tmp_path), 'val', kitti)


def test_prepare_checks_arguments_before_any_work(kitti, tmp_path):
  root, out = str(tmp_path / 'kitti'), tmp_path / 'out'
  _kitti_tree(root, kitti, seqs=(('00', 1),))
  with pytest.raises(ValueError, match=r"unknown splits \['vall'\]"):
    prepare.prepare('kitti', root, str(out), splits=('train', 'vall'))
  assert not out.exists()
  os.makedirs(tmp_path / 'empty' / 'sequences' / '00' / 'velodyne')
  with pytest.raises(FileNotFoundError, match='no kitti scan files'):
    prepare.prepare('kitti', str(tmp_path / 'empty'), str(out))


def test_prepare_removes_stale_splits_and_skips_junk(kitti, tmp_path):
  root, out = str(tmp_path / 'kitti'), str(tmp_path / 'out')
  _kitti_tree(root, kitti, seqs=(('00', 2), ('08', 1)))
  prepare.prepare('kitti', root, out, log=lambda m: None)
  assert os.path.isfile(arrays.split_path(out, 'val'))
  # Now the val sequence holds only junk: 8 random points, 1000 at the origin.
  val = os.path.join(root, 'sequences', '08', 'velodyne')
  rng = np.random.default_rng(0)
  kitti_io.write_bin(os.path.join(val, '000000.bin'),
                     rng.uniform(-20, 20, (8, 4)).astype(np.float32))
  kitti_io.write_bin(os.path.join(val, '000001.bin'), np.zeros((1000, 4), np.float32))
  logs = []
  meta = prepare.prepare('kitti', root, out, log=logs.append)
  assert meta['splits']['val'] == 0 and len(meta['skipped']['val']) == 2
  assert not os.path.isfile(arrays.split_path(out, 'val'))
  assert any('removed the old' in l for l in logs)
  assert all('valid pixels' in s['reason'] and 'not a full LiDAR scan' in s['reason']
             for s in meta['skipped']['val'])


def test_prepare_creates_nothing_before_its_inputs_check(kitti, tmp_path):
  """No empty --out from a root without sequences/ or scans."""
  out = tmp_path / 'out'
  (tmp_path / 'nosequences').mkdir()
  with pytest.raises(FileNotFoundError, match='sequences: no such directory'):
    prepare.prepare('kitti', str(tmp_path / 'nosequences'), str(out))
  assert not out.exists()
  os.makedirs(tmp_path / 'noscans' / 'sequences' / '00' / 'velodyne')
  with pytest.raises(FileNotFoundError, match='no kitti scan files'):
    prepare.prepare('kitti', str(tmp_path / 'noscans'), str(out))
  assert not out.exists()
  with pytest.raises(SystemExit, match='sequences: no such directory'):
    prepare_tool.main(['--dataset', 'kitti', '--root', str(tmp_path / 'nosequences'),
                       '--out', str(out)])
  assert not out.exists()


def test_meta_describes_every_array_beside_it(kitti, tmp_path):
  """Preparing one split keeps the others in meta.json."""
  root, out = str(tmp_path / 'kitti'), str(tmp_path / 'out')
  _kitti_tree(root, kitti, seqs=(('00', 2), ('08', 1), ('11', 3)))
  prepare.prepare('kitti', root, out, log=lambda m: None)
  first = arrays.read_meta(out)
  kitti_io.write_bin(os.path.join(root, 'sequences', '01', 'velodyne', '000000.bin'),
                     sensor_order_points(random_depth(kitti, seed=9), kitti))
  meta = prepare.prepare('kitti', root, out, splits=('train',), log=lambda m: None)
  assert meta == arrays.read_meta(out)
  assert meta['splits'] == {'train': 3, 'val': 1, 'test': 3}
  assert meta['skipped'] == first['skipped']
  for split, n in meta['splits'].items():
    assert len(arrays.load_split(out, split, kitti)) == n
  # Arrays of another sensor beside the split asked for: refused, untouched.
  np.save(arrays.split_path(out, 'val'), np.zeros((1, 32, 256), np.float32))
  with pytest.raises(ValueError, match=r'already holds val\.npy of shape \(1, 32, 256\)'):
    prepare.prepare('kitti', root, out, splits=('train',), log=lambda m: None)
  assert arrays.read_meta(out) == meta


def test_splits_are_written_scan_by_scan(kitti, tmp_path):
  """The array is the stacked scans, and the Python heap's peak
  while preparing does not grow with the number of scans (the old code
  held the split, then stacked it: 2 x 64 KB more per scan)."""
  import tracemalloc
  one = tmp_path / 'one.bin'
  kitti_io.write_bin(str(one), sensor_order_points(random_depth(kitti, seed=3), kitti))
  want = kitti_io.load_scan(str(one), kitti)[0]
  peaks = {}
  for n in (2, 20):
    root = tmp_path / f'n{n}'
    velodyne = root / 'sequences' / '00' / 'velodyne'
    velodyne.mkdir(parents=True)
    for i in range(n):
      shutil.copy(one, velodyne / f'{i:06d}.bin')
    out = str(tmp_path / f'out{n}')
    tracemalloc.start()
    prepare.prepare('kitti', str(root), out, splits=('train',), log=lambda m: None)
    peaks[n] = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    train = arrays.load_split(out, 'train', kitti)
    assert train.shape == (n, 64, 256)
    np.testing.assert_array_equal(np.asarray(train), np.broadcast_to(want, train.shape))
    assert not [f for f in os.listdir(out) if 'tmp' in f]
  assert peaks[20] - peaks[2] < 18 * 64 * 1024, peaks


def test_split_writer_header_and_abort(tmp_path):
  path = str(tmp_path / 'x.npy')
  w = arrays.SplitWriter(path, 1000, (3, 5))
  rows = np.arange(7 * 15, dtype=np.float32).reshape(7, 3, 5)
  for r in rows:
    w.append(r)
  assert w.close() == 7
  np.testing.assert_array_equal(np.load(path), rows)
  assert os.path.getsize(path) == w.offset + rows.nbytes
  w = arrays.SplitWriter(path, 2, (3, 5))
  w.append(rows[0])
  w.abort()
  np.testing.assert_array_equal(np.load(path), rows)  # the old file stays
  assert os.listdir(tmp_path) == ['x.npy']
