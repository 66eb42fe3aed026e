"""Velodyne packet captures (data/recordings.py, the optional
velodyne-decoder): a VLP-16 capture of known ranges written here packet by
packet, read back sweep by sweep and prepared into scans."""

import os
import struct
import sys

import numpy as np
import pytest

pytest.importorskip('velodyne_decoder')

from dusty_jax.data import arrays, prepare, read_sweeps, recordings  # noqa: E402
from dusty_jax.errors import DataError, UserError  # noqa: E402
from dusty_jax.sensor import get_sensor  # noqa: E402

# VLP-16 User Manual (63-9243 Rev. D), Table 9-1: each laser's elevation,
# in the order the lasers fire and a packet holds them.
VLP16_ELEVATION = (-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15)
STEP = 20  # hundredths of a degree per firing sequence (0.2 degrees at 600 rpm)
TURN = 36000
PACKETS_PER_TURN = TURN // (24 * STEP)  # 12 blocks of two firing sequences
START = 1_700_000_000.0  # capture time of the first packet (s)
# Points of a sweep: every firing of a turn, 16 returns each (velodyne-decoder's
# first sweep of a capture also takes the packet at its cut).
FULL_TURN = (16 * TURN // STEP, 16 * (TURN // STEP + 24))


def distance(laser):
  """The range (m) of every return of ``laser``."""
  return 4.0 + 0.25 * laser


def vlp16_packet(azimuth, stamp_us):
  """A VLP-16 data packet (strongest return) of 12 blocks from ``azimuth``."""
  body = b''
  for block in range(12):
    az = azimuth + 2 * STEP * block
    body += b'\xff\xee' + struct.pack('<H', az % TURN)
    for _ in range(2):  # firing sequences
      for laser in range(16):
        body += struct.pack('<HB', round(distance(laser) / 0.002), 100)
  return body + struct.pack('<I', stamp_us % 3_600_000_000) + bytes([0x37, 0x22])


def write_capture(path, packets, start_azimuth=0, extra=b''):
  """A classic pcap of ``packets`` VLP-16 data packets (UDP to port 2368),
  from ``start_azimuth``, 10 turns a second; ``extra``: one more record's
  payload after the first (as a GPS position packet comes between)."""
  def record(payload, t):
    udp = struct.pack('>HHHH', 8308, 2368, 8 + len(payload), 0) + payload
    ip = struct.pack('>BBHHHBBH4s4s', 0x45, 0, 20 + len(udp), 0, 0, 64, 17, 0,
                     bytes([192, 168, 1, 201]), bytes([255] * 4)) + udp
    frame = b'\xff' * 6 + b'\x60\x76\x88\x00\x00\x01' + b'\x08\x00' + ip
    return struct.pack('<IIII', int(t), round((t % 1) * 1e6), len(frame), len(frame)) + frame
  period = 0.1 / PACKETS_PER_TURN
  out = [struct.pack('<IHHiIII', 0xa1b2c3d4, 2, 4, 0, 0, 65535, 1)]
  for i in range(packets):
    t = START + i * period
    out.append(record(vlp16_packet(start_azimuth + 24 * STEP * i, round(i * period * 1e6)), t))
    if i == 0 and extra:
      out.append(record(extra, t))
  with open(path, 'wb') as f:
    f.write(b''.join(out))


def test_a_capture_reads_as_its_complete_sweeps(tmp_path):
  path = str(tmp_path / 'vlp16.pcap')
  # Three and a half turns from 90 degrees: three sweeps, the half turn after
  # them left out.
  write_capture(path, 7 * PACKETS_PER_TURN // 2, start_azimuth=9000, extra=b'\0' * 512)
  assert recordings.format_of(path) == 'velodyne'
  sweeps = list(read_sweeps(path))
  assert len(sweeps) == 3 == recordings.count_sweeps(path)
  for i, sweep in enumerate(sweeps):
    f = sweep.fields
    assert sweep.source == f'{path}#{i}'
    assert len(f['x']) in FULL_TURN
    azimuth = np.sort(np.mod(np.degrees(np.arctan2(f['y'], f['x'])), 360))
    assert np.diff(np.concatenate([azimuth, azimuth[:1] + 360])).max() < 0.25  # all round
    assert f['ring'].dtype == np.uint16 and set(f['ring'].tolist()) == set(range(16))
    r = np.sqrt(f['x'].astype(np.float64) ** 2 + f['y'] ** 2 + f['z'] ** 2)
    elevation = np.degrees(np.arcsin(f['z'] / r))
    laser = np.argmin(np.abs(elevation[:, None] - np.array(VLP16_ELEVATION)), 1)
    # The decoder's VLP-16 calibration places each beam's origin up to 11.2 mm off
    # the axis: 0.16 degrees at 4 m.
    np.testing.assert_allclose(elevation, np.array(VLP16_ELEVATION)[laser], atol=0.2)
    np.testing.assert_allclose(r, distance(laser), atol=0.003)
    assert abs(sweep.stamp_ns / 1e9 - (START + 0.1 * (i + 1))) < 0.002  # its last packet
  assert [s.source for s in read_sweeps(path, every=2)] == [f'{path}#0', f'{path}#2']
  with pytest.raises(DataError, match=r'vlp16\.pcap: a Velodyne capture has no topic'):
    next(read_sweeps(path, topic='/points'))


def test_a_capture_prepares_into_its_sweeps(tmp_path):
  vlp16 = get_sensor('vlp16')
  root, out = tmp_path / 'data', str(tmp_path / 'out')
  root.mkdir()
  write_capture(str(root / 'drive.pcap'), 7 * PACKETS_PER_TURN // 2)
  meta = prepare.prepare('files', str(root), out, sensor=get_sensor('vlp16'), log=lambda m: None)
  assert meta['splits']['train'] == 3 and not meta['skipped']['train']
  train = np.asarray(arrays.load_split(out, 'train', vlp16))
  assert train.shape == (3, 16, 1024)
  assert (train > 0).mean() > 0.95  # one firing in nearly every pixel
  for i, scan in enumerate(train):
    for row, elevation in enumerate(vlp16.elevation_deg):
      want = distance(VLP16_ELEVATION.index(round(elevation)))
      got = scan[row][scan[row] > 0]
      np.testing.assert_allclose(got, want, atol=0.003, err_msg=f'scan {i} row {row}')


def test_not_a_velodyne_capture(tmp_path):
  ouster_like = tmp_path / 'o.pcap'
  ouster_like.write_bytes(struct.pack('<IHHiIII', 0xa1b2c3d4, 2, 4, 0, 0, 65535, 1) +
                          struct.pack('<IIII', 0, 0, 8, 8) + b'\0' * 8)
  assert recordings.format_of(str(ouster_like)) is None  # a point file (Ouster's)
  (tmp_path / 'junk.pcap').write_bytes(b'not a capture')
  assert recordings.format_of(str(tmp_path / 'junk.pcap')) is None


def test_a_damaged_capture_is_one_line_and_keeps_the_sweeps_before(tmp_path):
  path = tmp_path / 'cut.pcap'
  write_capture(str(path), 4 * PACKETS_PER_TURN)
  data = path.read_bytes()
  path.write_bytes(data[:len(data) * 3 // 4] + b'\xff' * 7)  # a record cut short
  got = []
  try:
    for sweep in read_sweeps(str(path)):
      got.append(sweep)
  except DataError as e:
    assert str(e).startswith(f'{path}: cannot decode as a Velodyne capture after sweep')
    assert '\n' not in str(e)
  assert len(got) >= 1 and len(got[0].fields['x']) in FULL_TURN


def test_without_velodyne_decoder_one_line_says_what_to_install(tmp_path, monkeypatch):
  path = str(tmp_path / 'vlp16.pcap')
  write_capture(path, PACKETS_PER_TURN)
  monkeypatch.setitem(sys.modules, 'velodyne_decoder', None)
  with pytest.raises(UserError, match=r"vlp16\.pcap: decoding a Velodyne capture needs "
                     r"velodyne-decoder: pip install 'dusty_jax\[velodyne\]'$"):
    next(read_sweeps(path))
  with pytest.raises(UserError, match='needs velodyne-decoder'):
    prepare.prepare('files', str(tmp_path), str(tmp_path / 'out'), sensor=get_sensor('vlp16'))
  assert not os.path.exists(tmp_path / 'out')
