"""Recordings (data/recordings.py): ROS1 bags, ROS2 .db3 and .mcap files of
PointCloud2 sweeps written here with rosbags' own writers, read back sweep by
sweep and prepared into scans."""

import os
import pathlib
import sys

import numpy as np
import pytest

rosbags = pytest.importorskip('rosbags')
pointcloud2 = pytest.importorskip('pointcloud2')

from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from conftest import random_depth  # noqa: E402
from dusty_jax.data import arrays, prepare, read_points, read_sweeps, recordings  # noqa: E402
from dusty_jax.data import simulated_lidar, write_points  # noqa: E402
from dusty_jax.errors import DataError, UserError  # noqa: E402
from dusty_jax.sensor import get_sensor  # noqa: E402
from dusty_jax.tools import prepare as prepare_tool  # noqa: E402

ROS1 = get_typestore(Stores.ROS1_NOETIC)
ROS2 = get_typestore(Stores.ROS2_HUMBLE)
CLOUD = 'sensor_msgs/msg/PointCloud2'
STAMP = 1_700_000_000 * 10**9 + 123_456_789  # header stamp of sweep 0 (ns)
PERIOD = 100_000_000  # 10 Hz


def cloud_message(fields, stamp_ns, store, *, big_endian=False, height=1, pad=0):
  """A PointCloud2 of ``fields`` in ``store``'s types; ``pad`` bytes after each
  row (row_step > width * point_step), ``height`` rows."""
  n = len(next(iter(fields.values())))
  dtype = np.dtype([(k, v.dtype.newbyteorder('>' if big_endian else '<'))
                    for k, v in fields.items()])
  data = np.empty(n, dtype)
  for k, v in fields.items():
    data[k] = v
  width = n // height
  rows = data.tobytes()
  row = width * dtype.itemsize
  raw = b''.join(rows[i * row:(i + 1) * row] + b'\0' * pad for i in range(height))
  t = store.types
  header = dict(stamp=t['builtin_interfaces/msg/Time'](sec=stamp_ns // 10**9,
                                                        nanosec=stamp_ns % 10**9),
                frame_id='lidar')
  if store is ROS1:
    header['seq'] = 0
  point_fields = [t['sensor_msgs/msg/PointField'](name=f.name, offset=f.offset,
                                                  datatype=f.datatype, count=f.count)
                  for f in pointcloud2.fields_from_dtype(dtype.newbyteorder('='))]
  return t[CLOUD](header=t['std_msgs/msg/Header'](**header), height=height, width=width,
                  fields=point_fields, is_bigendian=big_endian, point_step=dtype.itemsize,
                  row_step=row + pad, data=np.frombuffer(raw, np.uint8), is_dense=False)


def write_recording(path, topics, **message_options):
  """Writes ``{topic: [fields, ...]}`` (or raw messages: (msgtype, message))
  as a ROS1 ``.bag``, or a ROS2 recording folder of one ``.mcap`` or
  ``.db3``; returns the storage file's path. Sweep i of a topic is stamped
  STAMP + i PERIOD and recorded 1 ms later."""
  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  ros1 = path.suffix == '.bag'
  store = ROS1 if ros1 else ROS2
  if ros1:
    writer = Writer1(path)
  else:
    plugin = StoragePlugin.MCAP if path.suffix == '.mcap' else StoragePlugin.SQLITE3
    writer = Writer2(path.with_suffix(''), version=9, storage_plugin=plugin)
  with writer:
    for topic, items in topics.items():
      msgtype = items[0][0] if isinstance(items[0], tuple) else CLOUD
      connection = writer.add_connection(topic, msgtype, typestore=store)
      for i, item in enumerate(items):
        stamp = STAMP + i * PERIOD
        message = (item[1] if isinstance(item, tuple) else
                   cloud_message(item, stamp, store, **message_options))
        raw = (store.serialize_ros1(message, msgtype) if ros1 else
               store.serialize_cdr(message, msgtype))
        writer.write(connection, stamp + 1_000_000, raw)
  return str(path if ros1 else path.with_suffix('') / path.name)


def driver_sweep(seed, n=500):
  """A sweep with the field types drivers write."""
  rng = np.random.default_rng(seed)
  return {
      'x': rng.uniform(-50, 50, n).astype(np.float32),
      'y': rng.uniform(-50, 50, n).astype(np.float32),
      'z': rng.uniform(-3, 3, n).astype(np.float32),
      'intensity': rng.uniform(0, 255, n).astype(np.float32),
      'ring': rng.integers(0, 32, n).astype(np.uint16),
      'return_type': rng.integers(0, 3, n).astype(np.uint8),
      'time': rng.uniform(0, 0.1, n),
      't_ns': rng.integers(-2**31, 2**31, n).astype(np.int32),
  }


def assert_same_fields(got, want):
  assert list(got) == list(want)
  for k in want:
    assert got[k].dtype == want[k].dtype, k
    np.testing.assert_array_equal(got[k], want[k], err_msg=k)


@pytest.mark.parametrize('name', ['r.bag', 'r.mcap', 'r.db3'])
def test_three_sweeps_read_back_as_written(tmp_path, name):
  sweeps = [driver_sweep(i) for i in range(3)]
  path = write_recording(tmp_path / name, {'/points': sweeps})
  got = list(read_sweeps(path))
  assert len(got) == 3 and recordings.count_sweeps(path) == 3
  for i, (sweep, want) in enumerate(zip(got, sweeps)):
    assert_same_fields(sweep.fields, want)
    assert sweep.stamp_ns == STAMP + i * PERIOD  # the header's, not the receive time
    assert sweep.source == f'{path}:/points#{i}'


def test_a_ros2_folder_reads_as_its_storage_file(tmp_path):
  sweeps = [driver_sweep(i, n=50) for i in range(3)]
  path = write_recording(tmp_path / 'r.mcap', {'/points': sweeps})
  folder = os.path.dirname(path)
  assert recordings.format_of(folder) == 'ros2'
  for sweep, want in zip(read_sweeps(folder), sweeps, strict=True):
    assert_same_fields(sweep.fields, want)


def test_every_keeps_every_nth_sweep(tmp_path):
  sweeps = [driver_sweep(i, n=20) for i in range(7)]
  path = write_recording(tmp_path / 'r.bag', {'/points': sweeps})
  got = list(read_sweeps(path, every=3))
  assert [s.source.rsplit('#')[1] for s in got] == ['0', '3', '6']
  assert recordings.count_sweeps(path, every=3) == 3
  for sweep, i in zip(got, (0, 3, 6)):
    assert_same_fields(sweep.fields, sweeps[i])
  for every in (0, -1, 1.5):
    with pytest.raises(ValueError, match='every must be a whole number >= 1'):
      next(read_sweeps(path, every=every))


def test_big_endian_organized_padded_clouds_read_right(tmp_path):
  want = driver_sweep(0, n=60)
  path = write_recording(tmp_path / 'r.mcap', {'/points': [want]}, big_endian=True,
                         height=3, pad=7)
  (sweep,) = read_sweeps(path)
  got = sweep.fields
  assert list(got) == list(want)
  for k in want:  # the values, in native byte order
    np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    assert got[k].dtype.isnative


def test_a_stamp_of_zero_takes_the_receive_time(tmp_path):
  path = tmp_path / 'r.bag'
  message = cloud_message(driver_sweep(0, n=10), 0, ROS1)
  with Writer1(path) as writer:
    connection = writer.add_connection('/points', CLOUD, typestore=ROS1)
    writer.write(connection, 42_000, ROS1.serialize_ros1(message, CLOUD))
  (sweep,) = read_sweeps(str(path))
  assert sweep.stamp_ns == 42_000


def _string(text):
  return ('std_msgs/msg/String', ROS2.types['std_msgs/msg/String'](data=text))


def test_topics_chosen_or_listed_in_one_line(tmp_path):
  a, b = [driver_sweep(i, n=10) for i in range(2)], [driver_sweep(5, n=10)]
  path = write_recording(tmp_path / 'r.mcap', {'/a': a, '/b': b, '/log': [_string('hi')]})
  with pytest.raises(DataError) as e:
    next(read_sweeps(path))
  assert str(e.value) == (f'{path}: 2 PointCloud2 topics, /a (2 messages), /b (1 messages); '
                          'name one (topic=, prepare --topic)')
  (got,) = read_sweeps(path, topic='/b')
  assert_same_fields(got.fields, b[0])
  with pytest.raises(DataError, match=rf'^{path}: no topic /c; its PointCloud2 topics: '
                     r'/a \(2 messages\), /b \(1 messages\)$'):
    next(read_sweeps(path, topic='/c'))
  with pytest.raises(DataError, match=rf'^{path}: /log is a std_msgs/msg/String, not a '
                     'PointCloud2'):
    next(read_sweeps(path, topic='/log'))
  only_log = write_recording(tmp_path / 'log.mcap', {'/log': [_string('a')]})
  with pytest.raises(DataError, match=rf'^{only_log}: no sensor_msgs/PointCloud2 topic '
                     r'\(its topics: /log \(std_msgs/msg/String\)\)$'):
    next(read_sweeps(only_log))


def test_a_bad_message_is_one_line_and_the_rest_still_read(tmp_path):
  good = [driver_sweep(i, n=10) for i in range(3)]
  path = tmp_path / 'r.bag'
  bad = cloud_message(good[1], STAMP, ROS1)
  bad.data = bad.data[:-4]  # a truncated cloud
  unknown = cloud_message(good[2], STAMP, ROS1)
  unknown.fields[0].datatype = 9
  no_xyz = cloud_message({'range': np.ones(4, np.float32)}, STAMP, ROS1)
  with Writer1(path) as writer:
    connection = writer.add_connection('/points', CLOUD, typestore=ROS1)
    for i, message in enumerate([cloud_message(good[0], STAMP, ROS1), bad, unknown, no_xyz,
                                 cloud_message(good[2], STAMP, ROS1)]):
      writer.write(connection, i + 1, ROS1.serialize_ros1(message, CLOUD))
  got = list(read_sweeps(str(path)))
  assert len(got) == 5
  assert_same_fields(got[0].fields, good[0])
  assert_same_fields(got[4].fields, good[2])
  with pytest.raises(DataError, match=rf'^{path}:/points#3: no x, y, z field; fields: range$'):
    got[3].fields
  with pytest.raises(DataError, match=rf'^{path}:/points#1: bad PointCloud2 layout \(.*'
                     r'10 x 1 points of \d+ bytes, \d+ bytes of data\)$'):
    got[1].fields
  with pytest.raises(DataError, match=rf"^{path}:/points#2: PointCloud2 field 'x' has "
                     'datatype 9'):
    got[2].fields


@pytest.mark.parametrize('name, content', [
    ('junk.bag', b'#ROSBAG V2.0\nnot a bag at all'), ('junk.mcap', b'\x89MCAP0\r\n' + b'x' * 40),
    ('junk.db3', b'SQLite format 3\0' + b'\0' * 50), ('empty.bag', b'')])
def test_an_unreadable_recording_is_one_line_naming_it(tmp_path, name, content):
  path = tmp_path / name
  path.write_bytes(content)
  with pytest.raises(DataError) as e:
    next(read_sweeps(str(path)))
  message = str(e.value)
  assert message.startswith(f'{path}: not a readable ROS recording (') and '\n' not in message
  with pytest.raises(DataError, match=rf'^{tmp_path}/none\.bag: no such file$'):
    next(read_sweeps(str(tmp_path / 'none.bag')))


def test_a_point_file_is_one_sweep(tmp_path):
  want = driver_sweep(0, n=30)
  path = str(tmp_path / 's.ply')
  write_points(path, want)
  (sweep,) = read_sweeps(path)
  assert sweep.stamp_ns is None and sweep.source == path
  assert_same_fields(sweep.fields, read_points(path))
  assert recordings.count_sweeps(path) == 1
  with pytest.raises(DataError, match=r's\.ply: a point file of one sweep has no topic'):
    next(read_sweeps(path, topic='/points'))


def test_without_rosbags_one_line_says_what_to_install(tmp_path, monkeypatch):
  path = write_recording(tmp_path / 'r.bag', {'/points': [driver_sweep(0, n=5)]})
  monkeypatch.setitem(sys.modules, 'rosbags.highlevel', None)  # its import then fails
  with pytest.raises(UserError, match=r"r\.bag: reading a ROS recording needs rosbags and "
                     r"pointcloud2: pip install 'dusty_jax\[ros\]'$"):
    next(read_sweeps(path))
  with pytest.raises(UserError, match='needs rosbags'):  # before anything is written
    prepare.prepare('files', str(tmp_path), str(tmp_path / 'out'), sensor=get_sensor('vlp16'))
  assert not (tmp_path / 'out').exists()


# --- prepare --dataset files with recordings ---------------------------------------------

def scan_sweep(depth, sensor):
  """The points of a depth image at the sensor's angles, with the Velodyne
  driver's fields (ring 0 the bottom beam)."""
  keep = depth > 0
  xyz = (depth[..., None] * simulated_lidar.ray_directions(sensor))[keep].astype(np.float32)
  ring = np.broadcast_to(np.arange(sensor.height)[::-1, None], depth.shape)[keep]
  return {'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2],
          'intensity': np.full(len(xyz), 7.0, np.float32), 'ring': ring.astype(np.uint16)}


@pytest.mark.parametrize('name', ['r.bag', 'r.mcap'])
def test_a_recording_of_three_sweeps_prepares_into_three_scans(tmp_path, name):
  vlp16 = get_sensor('vlp16')
  depths = [random_depth(vlp16, seed=i) for i in range(3)]
  root, out = tmp_path / 'data', str(tmp_path / 'out')
  write_recording(root / name, {'/velodyne_points': [scan_sweep(d, vlp16) for d in depths]})
  meta = prepare.prepare('files', str(root), out, sensor=get_sensor('vlp16'), log=lambda m: None)
  assert meta['splits']['train'] == 3 and not meta['skipped']['train']
  train = arrays.load_split(out, 'train', vlp16)
  assert train.shape == (3, 16, 1024)
  np.testing.assert_allclose(np.asarray(train), np.stack(depths), rtol=1e-5)


def test_prepare_tool_splits_recordings_by_file_and_thins_them(tmp_path, capsys):
  vlp16 = get_sensor('vlp16')
  root, out = tmp_path / 'data', str(tmp_path / 'out')
  depths = [random_depth(vlp16, seed=i) for i in range(5)]
  sweeps = [scan_sweep(d, vlp16) for d in depths]
  write_recording(root / 'a.bag', {'/points': sweeps, '/other': sweeps[:1]})
  write_recording(root / 'b.mcap', {'/points': sweeps[:2]})
  # One sweep of another sensor in a point file: skipped and said so.
  write_points(str(root / 'c.npy'), driver_sweep(0))
  (root / 'train.txt').write_text('a.bag\nc.npy\n')
  (root / 'test.txt').write_text('b/b.mcap\n')
  prepare_tool.main(['--dataset', 'files', '--root', str(root), '--out', out,
                     '--sensor', 'vlp16', '--topic', '/points', '--every', '2'])
  text = capsys.readouterr().out
  assert 'train: 3 scans written, 1 skipped' in text and 'test: 1 scans written' in text
  assert f'skipped: {root}/c.npy' in text
  train = arrays.load_split(out, 'train', vlp16)
  np.testing.assert_allclose(np.asarray(train), np.stack(depths[::2]), rtol=1e-5)
  # Without --topic the bag's two PointCloud2 topics are its one skip, naming both;
  # with no scan left the run fails on it and leaves the arrays written above.
  with pytest.raises(DataError, match=(
      rf'every scan file was skipped, nothing prepared; the first of 2: {root}/a\.bag: '
      r'2 PointCloud2 topics, /other \(1 messages\), /points \(5 messages\)')):
    prepare.prepare('files', str(root), out, sensor=get_sensor('vlp16'), splits=('train',),
                    log=lambda m: None)
  np.testing.assert_array_equal(arrays.load_split(out, 'train', vlp16), train)


def test_auto_estimates_from_a_recordings_sweeps(tmp_path):
  vlp16 = get_sensor('vlp16')
  root, out = tmp_path / 'data', str(tmp_path / 'out')
  write_recording(root / 'r.bag', {'/points': [scan_sweep(random_depth(vlp16, seed=i, drop=0.05),
                                                          vlp16) for i in range(3)]})
  logs = []
  meta = prepare.prepare('files', str(root), out, auto_sensor=True, log=logs.append)
  assert meta['splits']['train'] == 3 and meta['shape'][0] == 16
  assert any('from 3 training sweeps' in line for line in logs)
