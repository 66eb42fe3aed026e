"""Point cloud files: every format written and read back, every malformed
file refused in one line naming it, and the real sweeps of
../shared/data/sensors-sample and kitti-sample read (skipped where absent)."""

import importlib.util
import os
import sys
import warnings

import numpy as np
import pytest

from dusty_jax.data import ouster, points, read_points, ring_field, write_points
from dusty_jax.errors import DataError, UserError

SHARED = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..', 'shared', 'data')
SENSORS = os.path.join(SHARED, 'sensors-sample')
KITTI = os.path.join(SHARED, 'kitti-sample')
OUSTER_PCAP = os.path.join(SENSORS, 'OS-1-128_v2.3.0_1024x10_lb_n3.pcap')
OUSTER_JSON = os.path.join(SENSORS, 'OS-1-128_v2.3.0_1024x10.json')

HAS_PYPCD4 = importlib.util.find_spec('pypcd4') is not None
HAS_OUSTER = importlib.util.find_spec('ouster') is not None
needs_pcd = pytest.mark.skipif(not HAS_PYPCD4, reason="pypcd4 not installed (dusty_jax[pcd])")
needs_ouster = pytest.mark.skipif(not HAS_OUSTER, reason="ouster-sdk not installed (dusty_jax[ouster])")


def sample(*parts):
  path = os.path.join(*parts)
  if not os.path.exists(path):
    pytest.skip(f'{path}: sample absent (../shared)')
  return path


def sweep(n=300, seed=0):
  """A sweep of 16 rings at 1-80 m, with the fields drivers write."""
  rng = np.random.default_rng(seed)
  ring = rng.integers(0, 16, n).astype(np.uint16)
  elevation = np.deg2rad(-15 + 2 * ring.astype(np.float64))
  azimuth = rng.uniform(-np.pi, np.pi, n)
  r = rng.uniform(1, 80, n)
  return {
      'x': (r * np.cos(elevation) * np.cos(azimuth)).astype(np.float32),
      'y': (r * np.cos(elevation) * np.sin(azimuth)).astype(np.float32),
      'z': (r * np.sin(elevation)).astype(np.float32),
      'intensity': rng.uniform(0, 255, n).astype(np.float32),
      'ring': ring,
      'return_type': rng.integers(0, 3, n).astype(np.uint8),
      'time_stamp': 1.67e9 + rng.uniform(0, 0.1, n),
  }


def assert_fields_equal(got, want, names=None, atol=0.0):
  names = list(want) if names is None else names
  assert list(got) == names
  for k in names:
    assert got[k].shape == want[k].shape, k
    if atol:
      np.testing.assert_allclose(got[k], want[k], rtol=0, atol=atol, err_msg=k)
    else:
      np.testing.assert_array_equal(got[k], want[k], err_msg=k)


@pytest.mark.parametrize('name, encoding, atol', [
    pytest.param('s.pcd', 'binary', 0, marks=needs_pcd),
    pytest.param('s.pcd', 'binary_compressed', 0, marks=needs_pcd),
    # pypcd4 writes ASCII floats with 10 decimals.
    pytest.param('s.pcd', 'ascii', 1e-9, marks=needs_pcd),
    ('s.ply', 'binary', 0),
    ('s.ply', 'ascii', 0),
    ('s.npy', None, 0),
])
def test_every_field_round_trips(tmp_path, name, encoding, atol):
  fields = sweep()
  path = str(tmp_path / name)
  write_points(path, fields, encoding=encoding)
  got = read_points(path)
  assert_fields_equal(got, fields, atol=atol)
  assert {k: v.dtype for k, v in got.items()} == {k: v.dtype for k, v in fields.items()}


def test_the_written_encoding_is_the_one_asked(tmp_path):
  fields = sweep(50)
  kinds = {}
  for enc in (points.PCD_ENCODINGS if HAS_PYPCD4 else ()):
    write_points(str(tmp_path / f'{enc}.pcd'), fields, encoding=enc)
    kinds[enc] = open(tmp_path / f'{enc}.pcd', 'rb').read().split(b'\nDATA ')[1].split()[0]
  for enc in points.PLY_ENCODINGS:
    write_points(str(tmp_path / f'{enc}.ply'), fields, encoding=enc)
    kinds[enc + ' ply'] = open(tmp_path / f'{enc}.ply', 'rb').read().split(b'format ')[1].split()[0]
  assert kinds.pop('binary ply') == b'binary_little_endian'
  assert kinds.pop('ascii ply') == b'ascii'
  assert all(v == k.encode() for k, v in kinds.items()), kinds
  with pytest.raises(ValueError, match=r'x\.ply: encoding .binary_compressed'):
    write_points(str(tmp_path / 'x.ply'), fields, encoding='binary_compressed')


def test_nuscenes_and_kitti_keep_their_fixed_fields(tmp_path):
  fields = sweep()
  write_points(str(tmp_path / 'n.pcd.bin'), fields)
  got = read_points(str(tmp_path / 'n.pcd.bin'))
  assert os.path.getsize(tmp_path / 'n.pcd.bin') == 20 * len(fields['x'])
  want = {k: fields[k].astype(np.float32) for k in points.NUSCENES_FIELDS}
  assert_fields_equal(got, want)
  np.testing.assert_array_equal(ring_field(got), fields['ring'])

  write_points(str(tmp_path / 'k.bin'), fields)
  got = read_points(str(tmp_path / 'k.bin'))
  assert_fields_equal(got, {k: fields[k] for k in points.KITTI_FIELDS})
  assert ring_field(got) is None

  del fields['intensity']  # written as 0
  write_points(str(tmp_path / 'k0.bin'), fields)
  assert not read_points(str(tmp_path / 'k0.bin'))['intensity'].any()
  del fields['ring']
  with pytest.raises(ValueError, match=r'n2\.pcd\.bin: a nuScenes .pcd.bin needs a ring field'):
    write_points(str(tmp_path / 'n2.pcd.bin'), fields)


@pytest.mark.parametrize('columns', [3, 4, 5])
def test_plain_npy_columns_are_x_y_z_intensity_ring(tmp_path, columns):
  arr = np.random.default_rng(1).uniform(-50, 50, (40, columns))
  np.save(tmp_path / 'a.npy', arr)
  got = read_points(str(tmp_path / 'a.npy'))
  assert list(got) == list(points.NPY_COLUMNS[:columns])
  for i, k in enumerate(got):
    np.testing.assert_array_equal(got[k], arr[:, i])
    assert got[k].flags.c_contiguous


def test_placeholders_and_nan_points_are_kept(tmp_path):
  """The reader drops nothing: nuScenes' points at the origin and an
  organized PCD's NaN points reach the unfolding, which drops and counts."""
  fields = sweep(20)
  fields['x'][:5] = fields['y'][:5] = fields['z'][:5] = 0
  write_points(str(tmp_path / 'n.pcd.bin'), fields)
  got = read_points(str(tmp_path / 'n.pcd.bin'))
  assert len(got['x']) == 20 and (got['x'][:5] == 0).all() and (got['z'][:5] == 0).all()

  fields['x'][5:8] = fields['y'][5:8] = fields['z'][5:8] = np.nan
  for name, enc in ([('b.pcd', 'binary'), ('a.pcd', 'ascii'), ('c.pcd', 'binary_compressed')]
                    if HAS_PYPCD4 else []) + [('p.ply', 'binary'), ('p.npy', None)]:
    write_points(str(tmp_path / name), fields, encoding=enc)
    got = read_points(str(tmp_path / name))
    assert len(got['x']) == 20, name
    np.testing.assert_array_equal(np.isnan(got['z']), np.isnan(fields['z']), err_msg=name)

  write_points(str(tmp_path / 'k.bin'), fields)  # KITTI's reader refuses NaN, as ever
  with pytest.raises(ValueError, match=r'k\.bin: 3 of 20 points have NaN'):
    read_points(str(tmp_path / 'k.bin'))


PCD_HEADER = """# .PCD v0.7 - Point Cloud Data file format
VERSION 0.7
FIELDS {fields}
SIZE {size}
TYPE {type}
COUNT {count}
WIDTH {width}
HEIGHT {height}
VIEWPOINT 0 0 0 1 0 0 0
POINTS {points}
DATA {data}
"""


def pcd_file(path, body=b'', fields='x y z ring', size='4 4 4 2', type='F F F U',
             count='1 1 1 1', width=2, height=1, points=2, data='ascii', drop=()):
  header = PCD_HEADER.format(fields=fields, size=size, type=type, count=count, width=width,
                             height=height, points=points, data=data)
  header = ''.join(line + '\n' for line in header.splitlines() if line.split()[0] not in drop)
  path.write_bytes(header.encode() + body)
  return str(path)


@needs_pcd
def test_pcd_width_0_height_0_as_a_driver_writes_it(tmp_path):
  fields = sweep(30)
  path = tmp_path / 'w0.pcd'
  write_points(str(path), fields)
  raw = path.read_bytes()
  assert b'WIDTH 30\nHEIGHT 1\n' in raw
  path.write_bytes(raw.replace(b'WIDTH 30\nHEIGHT 1\n', b'WIDTH 0\nHEIGHT 0\n'))
  assert_fields_equal(read_points(str(path)), fields)


@needs_pcd
@pytest.mark.parametrize('encoding', ['binary', 'binary_compressed'])
def test_pcd_header_of_more_than_ten_lines(tmp_path, encoding):
  """pypcd4 alone reads ten header lines and then takes the rest for data."""
  fields = sweep(30)
  path = tmp_path / 'long.pcd'
  write_points(path, fields, encoding=encoding)
  raw = path.read_bytes()
  path.write_bytes(raw.replace(b'VERSION 0.7\n', b'VERSION 0.7\nSOURCE driver 2.1\n'
                                                  b'# a comment\nSTAMP 1673400472\n'))
  assert path.read_bytes().count(b'\n', 0, path.read_bytes().index(b'DATA')) == 12
  assert_fields_equal(read_points(path), fields)  # a pathlib.Path too


@needs_pcd
def test_pcd_ascii_rows_split_at_any_whitespace(tmp_path):
  body = b'1.5 2 3 7 \n4\t5  6 8\t\n'  # trailing spaces and tabs, as some writers leave
  got = read_points(pcd_file(tmp_path / 'a.pcd', body))
  np.testing.assert_array_equal(got['x'], [1.5, 4])
  np.testing.assert_array_equal(got['ring'], [7, 8])
  assert got['ring'].dtype == np.uint16
  one = read_points(pcd_file(tmp_path / 'one.pcd', b'1 2 3 4\n', width=1, points=1))
  assert one['x'].shape == (1,)


@needs_pcd
def test_pcd_padding_dropped_and_counted_fields_split(tmp_path):
  """A '_' field pads (no data); a field of COUNT 3 becomes three columns
  named as pypcd4 names them."""
  body = b'1 2 3 9 10 11 12\n4 5 6 9 13 14 15\n'
  got = read_points(pcd_file(tmp_path / 'p.pcd', body, fields='x y z _ normal',
                             size='4 4 4 4 4', type='F F F F F', count='1 1 1 1 3'))
  assert list(got) == ['x', 'y', 'z', 'normal__0000', 'normal__0001', 'normal__0002']
  np.testing.assert_array_equal(got['normal__0002'], [12, 15])


@needs_pcd
def test_pcd_with_no_points_reads_empty(tmp_path):
  got = read_points(pcd_file(tmp_path / 'e.pcd', width=0, points=0, data='binary'))
  assert list(got) == ['x', 'y', 'z', 'ring'] and all(len(v) == 0 for v in got.values())


def test_ring_field_picks_the_drivers_name():
  xyz = {k: np.zeros(3, np.float32) for k in 'xyz'}
  assert ring_field(xyz) is None
  np.testing.assert_array_equal(ring_field({**xyz, 'channel': np.array([3, 1, 2], np.uint16)}),
                                [3, 1, 2])
  got = ring_field({**xyz, 'beam': np.array([0., 5., 127.], np.float32),
                    'ring': np.array([1, 2, 3], np.uint8)})
  np.testing.assert_array_equal(got, [1, 2, 3])  # 'ring' first
  assert got.dtype == np.int64
  np.testing.assert_array_equal(ring_field({**xyz, 'ring': np.array([0., 31., 7.])}), [0, 31, 7])
  for bad in ([0.5, 1, 2], [np.nan, 1, 2]):
    with pytest.raises(DataError, match='scan.pcd: the ring field .ring. holds values that'):
      ring_field({**xyz, 'ring': np.array(bad)}, 'scan.pcd')


def _one_line_naming(excinfo, path):
  msg = str(excinfo.value)
  assert msg.startswith(str(path) + ':'), msg
  assert '\n' not in msg, msg
  return msg


def _malformed(tmp_path):
  """(file name, writer of the file, the message's problem): each case."""
  fields = sweep(10)
  cases = [
      ('scan.xyz', lambda p: p.write_bytes(b'1 2 3\n'), "unknown point cloud format '.xyz'"),
      ('scan', lambda p: p.write_bytes(b'1 2 3\n'), "unknown point cloud format '\\(no extension\\)'"),
      ('gone.pcd', None, 'no such file'),
      ('short.bin', lambda p: p.write_bytes(b'\0' * 70), 'size 70 bytes is not a multiple of 16'),
      ('empty.bin', lambda p: p.write_bytes(b''), 'empty file'),
      ('short.pcd.bin', lambda p: p.write_bytes(b'\0' * 50), 'size 50 bytes is not a multiple of 20'),
      ('empty.pcd.bin', lambda p: p.write_bytes(b''), 'empty file'),
      ('bad.ply', lambda p: p.write_bytes(b'plx\nformat ascii 1.0\nend_header\n'), 'bad PLY file'),
      ('noverts.ply', lambda p: p.write_bytes(
          b'ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n'
          b'end_header\n3 0 1 2\n'), 'PLY file without a vertex element'),
      ('noxyz.ply', lambda p: p.write_bytes(
          b'ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n'),
       'no y, z field; fields: x'),
      ('cols2.npy', lambda p: np.save(p, np.zeros((5, 2))), r'expected an \(N, 3..5\) array'),
      ('cols7.npy', lambda p: np.save(p, np.zeros((5, 7))), r'expected an \(N, 3..5\) array'),
      ('text.npy', lambda p: np.save(p, np.array(['a', 'b'])), r'expected an \(N, 3..5\) array'),
      ('objects.npy', lambda p: np.save(p, np.array([{}], dtype=object), allow_pickle=True),
       'not a readable .npy array'),
      ('archive.npy', lambda p: p.write_bytes(_npz_bytes(tmp_path)), 'a .npz archive'),
      ('nox.npy', lambda p: np.save(p, np.zeros(4, [('a', 'f4'), ('y', 'f4'), ('z', 'f4')])),
       'no x field; fields: a, y, z'),
      ('normals.npy', lambda p: np.save(p, np.zeros(4, [('x', 'f4'), ('y', 'f4'), ('z', 'f4'),
                                                         ('normal', 'f4', 3)])),
       r'fields must be 1-D arrays of one length, got shapes \[\(4,\), \(4, 3\)\]'),
  ]
  plybin = tmp_path / 'whole.ply'
  write_points(str(plybin), fields)
  cases.append(('cut.ply', lambda p: p.write_bytes(plybin.read_bytes()[:-7]), 'bad PLY file'))
  if HAS_PYPCD4:
    whole = tmp_path / 'whole.pcd'
    write_points(str(whole), fields)
    packed = tmp_path / 'packed.pcd'
    write_points(str(packed), fields, encoding='binary_compressed')
    raw = packed.read_bytes()
    data_at = raw.index(b'DATA binary_compressed\n') + len('DATA binary_compressed\n')
    cases += [
        ('nofields.pcd', lambda p: pcd_file(p, b'1 2 3 4\n', drop=('FIELDS',)),
         'PCD header has no FIELDS line'),
        ('notype.pcd', lambda p: pcd_file(p, b'1 2 3 4\n', drop=('TYPE',)),
         'PCD header has no TYPE line'),
        ('nodata.pcd', lambda p: pcd_file(p, drop=('DATA',)), 'PCD header without a DATA line'),
        ('lzma.pcd', lambda p: pcd_file(p, data='binary_lzma'),
         "PCD DATA 'binary_lzma' is not supported"),
        ('sizes.pcd', lambda p: pcd_file(p, b'1 2 3 4\n', size='4 4 4'),
         'PCD header has 4 FIELDS but 3 SIZE'),
        ('type.pcd', lambda p: pcd_file(p, b'1 2 3 4\n', type='F F F Q'), 'bad PCD header'),
        ('f16.pcd', lambda p: pcd_file(p, b'1 2 3 4\n', size='4 4 4 2', type='F F F F'),
         'PCD TYPE F of SIZE 2 is not supported'),
        ('row.pcd', lambda p: pcd_file(p, b'1 2 3 4\n5 6 7\n'), 'bad PCD ascii data'),
        ('few.pcd', lambda p: pcd_file(p, b'1 2 3 4\n', points=3), 'POINTS 3, the data holds 1'),
        ('cut.pcd', lambda p: p.write_bytes(whole.read_bytes()[:-9]),
         'binary data of 261 bytes, short of the 270 that POINTS 10 of 27 bytes'),
        ('corrupt.pcd', lambda p: p.write_bytes(raw[:data_at + 8] + b'\xff' * (len(raw) - data_at - 8)),
         'bad PCD binary_compressed data'),
        ('garbage.pcd', lambda p: p.write_bytes(b'\x89PNG\r\n\x1a\n' + b'\xff' * 100),
         'not a PCD file'),
    ]
  return cases


def _npz_bytes(tmp_path):
  np.savez(tmp_path / 'z.npz', a=np.zeros(3))
  return (tmp_path / 'z.npz').read_bytes()


def test_every_malformed_file_gives_one_line_naming_it(tmp_path):
  cases = _malformed(tmp_path)
  assert len(cases) >= 16
  for name, make, problem in cases:
    path = tmp_path / name
    if make:
      make(path)
    with pytest.raises(DataError, match=problem) as excinfo:
      read_points(str(path))
    _one_line_naming(excinfo, path)


def test_what_a_writer_cannot_write_is_refused_naming_the_file(tmp_path):
  fields = sweep(10)
  with pytest.raises(ValueError, match=r"s\.las: cannot write '\.las'"):
    write_points(str(tmp_path / 's.las'), fields)
  with pytest.raises(ValueError, match=r"s\.ply: field type 'u8' not in"):
    write_points(str(tmp_path / 's.ply'), {**fields, 't': np.zeros(10, np.uint64)})
  with pytest.raises(ValueError, match=r's\.npy: fields must be 1-D arrays of one length'):
    write_points(str(tmp_path / 's.npy'), {**fields, 'x': fields['x'][:9]})
  with pytest.raises(ValueError, match=r's\.npy: no z field'):
    write_points(str(tmp_path / 's.npy'), {'x': fields['x'], 'y': fields['y']})
  assert not list(tmp_path.iterdir())


def test_the_options_of_a_pcap_refused_elsewhere(tmp_path):
  path = str(tmp_path / 'a.npy')
  np.save(path, np.zeros((3, 3)))
  with pytest.raises(DataError, match='a.npy: metadata and frame are for an Ouster .pcap only'):
    read_points(path, frame=1)


def test_without_pypcd4_one_line_says_what_to_install(tmp_path, monkeypatch):
  monkeypatch.setitem(sys.modules, 'pypcd4', None)  # import pypcd4 then fails
  with pytest.raises(UserError, match=r"x\.pcd: PCD files need pypcd4: pip install 'dusty_jax\[pcd\]'"):
    read_points(pcd_file(tmp_path / 'x.pcd', b'1 2 3 4\n5 6 7 8\n'))


def test_without_the_ouster_sdk_one_line_says_what_to_install(tmp_path, monkeypatch):
  for name in ('ouster', 'ouster.sdk', 'ouster.sdk.core'):  # even if imported before
    monkeypatch.setitem(sys.modules, name, None)
  pcap = tmp_path / 'x.pcap'
  pcap.write_bytes(b'\0' * 24)
  with pytest.raises(UserError, match=r"x\.pcap: reading an Ouster recording needs ouster-sdk: "
                                      r"pip install 'dusty_jax\[ouster\]'"):
    read_points(str(pcap))


def test_ouster_metadata_found_beside_the_pcap(tmp_path):
  pcap = tmp_path / 'rec_lb_n3.pcap'
  pcap.write_bytes(b'')
  with pytest.raises(DataError, match=r'rec_lb_n3.pcap: no metadata rec_lb_n3.json beside it and '
                                      'no json file in its folder'):
    ouster.find_metadata(str(pcap))
  (tmp_path / 'rec.json').write_text('{}')
  assert ouster.find_metadata(str(pcap)) == str(tmp_path / 'rec.json')  # the one json
  (tmp_path / 'other.json').write_text('{}')
  with pytest.raises(DataError, match=r'2 json files \(other.json, rec.json\)'):
    ouster.find_metadata(str(pcap))
  (tmp_path / 'rec_lb_n3.json').write_text('{}')
  assert ouster.find_metadata(str(pcap)) == str(tmp_path / 'rec_lb_n3.json')  # same stem first


# ---- The real sweeps (../shared; skipped where absent) ----

def _elevation(f):
  return np.degrees(np.arctan2(f['z'], np.hypot(f['x'], f['y'])))


@needs_pcd
def test_vlp16_sample_read():
  """Velodyne numbers rings bottom first; this indoor sweep has no point on
  ring 0 (-15 degrees), so 15 ring values, each exactly on its beam."""
  f = read_points(sample(SENSORS, 'vlp16_ring.pcd'))
  assert list(f) == ['x', 'y', 'z', 'intensity', 'ring', 'azimuth', 'distance', 'return_type',
                     'time_stamp']
  assert len(f['x']) == 14673 and all(len(v) == 14673 for v in f.values())
  ring = ring_field(f)
  assert set(np.unique(ring)) == set(range(1, 16))
  el = _elevation(f)
  for r in range(1, 16):
    np.testing.assert_allclose(el[ring == r], -15 + 2 * r, atol=1e-3)
  assert np.isfinite(f['x']).all()


@needs_pcd
def test_pandar_xt16_sample_read():
  """Hesai numbers channels top first (+15 degrees is channel 0)."""
  f = read_points(sample(SENSORS, 'pandar_xt16_channel.pcd'))
  assert len(f['x']) == 26287
  assert f['intensity'].dtype == np.uint8 and f['time_stamp'].dtype == np.uint32
  ring = ring_field(f)
  assert set(np.unique(ring)) == set(range(16))
  el = _elevation(f)
  for r in range(16):
    np.testing.assert_allclose(el[ring == r], 15 - 2 * r, atol=1e-3)
  np.testing.assert_allclose(np.rad2deg(f['elevation']), el, atol=1e-3)


def test_kitti_sample_read():
  path = sample(KITTI, '000000.bin')
  f = read_points(path)
  assert list(f) == list(points.KITTI_FIELDS)
  assert len(f['x']) == os.path.getsize(path) // 16
  assert 0 <= f['intensity'].min() and f['intensity'].max() <= 1


@needs_ouster
def test_ouster_sample_read():
  """128 beams, ring 0 the top one; from the lidar frame's origin the points
  sit on their beams' metadata elevations (ouster.py's docstring)."""
  pcap, meta = sample(OUSTER_PCAP), sample(OUSTER_JSON)
  f = read_points(pcap)  # the one json in the folder
  n = len(f['x'])
  assert 100_000 < n < 128 * 1024 and all(len(v) == n for v in f.values())
  assert (f['range'] > 0).all()
  ring = ring_field(f)
  assert set(np.unique(ring)) == set(range(128))
  cal = ouster.read_metadata(meta)
  alt = cal['beam_altitude_angles']
  assert alt.shape == (128,) and (np.diff(alt) < 0).all()  # top beam first
  assert cal['lidar_origin_to_beam_origin_mm'] == pytest.approx(15.806)
  assert cal['beam_to_lidar_transform'][0, 3] == pytest.approx(15.806)
  assert cal['lidar_to_sensor_transform'][2, 3] == pytest.approx(36.18)
  assert (cal['rings'], cal['columns']) == (128, 1024)
  el = _elevation(f)
  nearest = np.abs(el[:, None] - alt[None]).argmin(1)
  assert np.mean(nearest == ring) > 0.999
  np.testing.assert_allclose(np.linalg.norm(np.stack([f['x'], f['y'], f['z']], 1), axis=1),
                             f['range'] / 1000, atol=0.02)  # beam origins are 16 mm out
  other = read_points(pcap, metadata=meta, frame=2)
  assert len(other['x']) != n
  with pytest.raises(DataError, match='no complete sweep 3; the recording holds 3 complete and 0'):
    read_points(pcap, frame=3)


@needs_ouster
def test_ouster_dual_returns_keep_both(tmp_path):
  _, core = ouster._sdk('test')
  info = core.SensorInfo(open(sample(OUSTER_JSON)).read())
  with warnings.catch_warnings():
    warnings.simplefilter('ignore', FutureWarning)
    frame = core.LidarFrame(info.h, info.w, core.UDPProfileLidar.RNG19_RFL8_SIG16_NIR16_DUAL, 16)
  for name in ('RANGE', 'RANGE2', 'NEAR_IR', 'REFLECTIVITY', 'REFLECTIVITY2'):
    frame.field(name)[:] = 0
  frame.field('RANGE')[5, 7] = 10_000
  frame.field('RANGE2')[5, 7] = 20_000
  frame.field('RANGE2')[6, 8] = 5_000
  frame.field('REFLECTIVITY2')[6, 8] = 42
  frame.field('NEAR_IR')[6, 8] = 300
  f = ouster.frame_fields(frame, info, core.XYZLut(info))
  np.testing.assert_array_equal(f['return_type'], [0, 1, 1])
  np.testing.assert_array_equal(f['ring'], [5, 5, 6])
  np.testing.assert_array_equal(f['range'], [10_000, 20_000, 5_000])
  np.testing.assert_array_equal(f['intensity'], [0, 0, 42])
  np.testing.assert_array_equal(f['near_ir'], [0, 0, 300])
  xyz = np.stack([f['x'], f['y'], f['z']], 1)
  assert np.linalg.norm(xyz[1]) == pytest.approx(2 * np.linalg.norm(xyz[0]), rel=0.01)


@needs_ouster
def test_malformed_ouster_recordings_give_one_line(tmp_path):
  meta = tmp_path / 'rec.json'
  meta.write_bytes(open(sample(OUSTER_JSON), 'rb').read())
  junk = tmp_path / 'junk.pcap'
  junk.write_bytes(b'hello\n')
  with pytest.raises(DataError, match='cannot open as an Ouster recording') as e:
    read_points(str(junk), metadata=str(meta))
  _one_line_naming(e, junk)
  cut = tmp_path / 'cut.pcap'  # the capture's header and less than one sweep
  cut.write_bytes(open(sample(OUSTER_PCAP), 'rb').read()[:20_000])
  with pytest.raises(DataError, match='no complete sweep 0; the recording holds 0 complete '
                                      'and 1 partial') as e:
    read_points(str(cut), metadata=str(meta))
  _one_line_naming(e, cut)
  longer = tmp_path / 'longer.pcap'  # a sweep and most of the next
  longer.write_bytes(open(sample(OUSTER_PCAP), 'rb').read()[:1_000_000])
  assert len(np.unique(read_points(str(longer), metadata=str(meta))['measurement_id'])) == 1024
  with pytest.raises(DataError, match='no complete sweep 1; the recording holds 1 complete '
                                      'and 1 partial'):
    read_points(str(longer), metadata=str(meta), frame=1)
  bad = tmp_path / 'bad.json'
  bad.write_text('{"beam_altitude_angles": []}')
  with pytest.raises(DataError, match='not an Ouster metadata file') as e:
    read_points(str(cut), metadata=str(bad))
  _one_line_naming(e, bad)
  with pytest.raises(DataError, match='cannot read the Ouster metadata') as e:
    read_points(str(cut), metadata=str(tmp_path / 'gone.json'))
