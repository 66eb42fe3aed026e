"""Recordings of many sweeps, read one sweep after another.

:func:`read_sweeps` yields the sweeps of

  ``.bag``            a ROS1 bag,
  ``.db3``, ``.mcap`` a ROS2 storage file, or the folder ``ros2 bag record``
                      writes (with its metadata.yaml),

each a sensor_msgs/PointCloud2 message of one topic, read with the optional
pure-Python ``rosbags`` and ``pointcloud2`` (``pip install 'dusty_jax[ros]'``;
no ROS install); of

  ``.pcap``           a Velodyne packet capture (one whose first packets
                      include a Velodyne data packet: VELODYNE_RECORD
                      bytes), decoded by the optional ``velodyne-decoder``
                      (``pip install 'dusty_jax[velodyne]'``), which finds
                      the model in the packets and cuts a sweep at each full
                      turn from the first packet (the packets after the
                      last full turn are left out);

and of every point file :func:`points.read_points` reads (one sweep each;
an Ouster ``.pcap`` gives its first complete sweep).

Each :class:`Sweep` carries its fields as read_points gives them: every
PointField under the driver's name and in its dtype (one of count k as
``name_0`` .. ``name_{k-1}``), an organized cloud (height > 1) row after
row with its NaN points kept, as an organized PCD's are; and its time
stamp in nanoseconds: the message header's, or the recording's receive time
where the header's is zero. A Velodyne sweep has velodyne-decoder's fields
(VELODYNE_FIELDS: time in seconds from the stamp, column, ring, return_type)
and the capture time of its last packet.

A recording that cannot be opened, or whose topic is ambiguous or absent,
raises one DataError naming it (and its topics). A message that cannot be
decoded does not end the iteration: its Sweep raises that DataError when its
fields are asked for, so a caller can skip it and go on (prepare does).
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib

import numpy as np

from dusty_jax.data import points
from dusty_jax.errors import DataError, UserError

RECORDING_FORMATS = ('.bag', '.db3', '.mcap')
ROS2_METADATA = 'metadata.yaml'  # what makes a folder a ROS2 recording
POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'  # rosbags' name of the type in ROS1 and ROS2

INSTALL = "pip install 'dusty_jax[ros]'"
VELODYNE_INSTALL = "pip install 'dusty_jax[velodyne]'"

# A Velodyne data packet as captured: Ethernet (14), IPv4 (20) and UDP (8)
# headers and its 1206 bytes (every Velodyne model since the HDL-32E).
VELODYNE_RECORD = 14 + 20 + 8 + 1206
PCAP_MAGIC = {b'\xd4\xc3\xb2\xa1': '<', b'\xa1\xb2\xc3\xd4': '>',  # microsecond stamps
              b'\x4d\x3c\xb2\xa1': '<', b'\xa1\xb2\x3c\x4d': '>'}  # nanosecond stamps
PCAP_PEEK = 64  # packets looked at for a Velodyne one (position packets come between)
# velodyne-decoder's columns of a decoded sweep, and the dtype each is kept in.
VELODYNE_FIELDS = {'x': np.float32, 'y': np.float32, 'z': np.float32,
                   'intensity': np.float32, 'time': np.float32, 'column': np.uint32,
                   'ring': np.uint16, 'return_type': np.uint8}


@dataclasses.dataclass(frozen=True, eq=False)
class Sweep:
  """One sweep of a recording: ``source`` names it (``FILE`` for a point
  file, ``FILE:TOPIC#INDEX`` for a message, INDEX counting the topic's
  messages from 0, ``FILE#INDEX`` for a Velodyne capture's), ``stamp_ns``
  its time (None for a point file)."""

  source: str
  stamp_ns: int | None
  _fields: dict | None = dataclasses.field(default=None, repr=False)
  _error: str | None = dataclasses.field(default=None, repr=False)

  @property
  def fields(self) -> dict[str, np.ndarray]:
    """{name: (N,) array} with x, y, z; DataError where it could not be decoded."""
    if self._error is not None:
      raise DataError(self._error)
    return self._fields


def format_of(path: str) -> str | None:
  """The recording format of ``path`` ('.bag', '.db3', '.mcap', 'ros2' for
  a ROS2 recording's folder, 'velodyne' for a Velodyne capture), or None."""
  if os.path.isdir(path):
    return 'ros2' if os.path.isfile(os.path.join(path, ROS2_METADATA)) else None
  suffix = os.path.splitext(path)[1].lower()
  if suffix == '.pcap':
    return 'velodyne' if _velodyne_capture(path) else None
  return suffix if suffix in RECORDING_FORMATS else None


def _velodyne_capture(path: str) -> bool:
  """Whether a classic pcap file holds a Velodyne data packet among its first
  PCAP_PEEK records (an Ouster capture's are thousands of bytes, or 90)."""
  try:
    with open(path, 'rb') as f:
      head = f.read(24)
      order = PCAP_MAGIC.get(head[:4])
      if order is None:
        return False
      for _ in range(PCAP_PEEK):
        record = f.read(16)
        if len(record) < 16:
          return False
        size = int.from_bytes(record[8:12], 'little' if order == '<' else 'big')
        if size == VELODYNE_RECORD:
          return True
        f.seek(size, os.SEEK_CUR)
  except OSError:
    return False
  return False


def _rosbags(path: str):
  """rosbags' AnyReader and a typestore for ROS2 files without message
  definitions, and pointcloud2; or one UserError saying how to install them."""
  try:
    # rosbags and pointcloud2 are optional (the [ros] extra).
    import pointcloud2
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
  except ImportError:
    raise UserError(f'{path}: reading a ROS recording needs rosbags and pointcloud2: '
                    f'{INSTALL}') from None
  return AnyReader, get_typestore(Stores.ROS2_HUMBLE), pointcloud2


def _velodyne(path: str):
  """velodyne-decoder, or one UserError saying how to install it."""
  try:
    # velodyne-decoder is optional (the [velodyne] extra; compiled, with dpkt).
    import velodyne_decoder
  except ImportError:
    raise UserError(f'{path}: decoding a Velodyne capture needs velodyne-decoder: '
                    f'{VELODYNE_INSTALL}') from None
  return velodyne_decoder


def require(path: str):
  """Raises the UserError of a missing extra ([ros], [velodyne]) for a
  recording ``path``."""
  kind = format_of(path)
  if kind == 'velodyne':
    _velodyne(path)
  elif kind:
    _rosbags(path)


def _one_line(e: Exception) -> str:
  return ' '.join(str(e).split()) or type(e).__name__


def _open(path: str):
  """An open rosbags AnyReader of ``path``, and the module pointcloud2."""
  any_reader, typestore, pointcloud2 = _rosbags(path)
  try:
    reader = any_reader([pathlib.Path(path)], default_typestore=typestore)
    reader.open()
  except Exception as e:  # rosbags' reader errors, sqlite's, mcap's, a missing file
    raise DataError(f'{path}: not a readable ROS recording ({type(e).__name__}: '
                    f'{_one_line(e)})') from None
  return reader, pointcloud2


def _topic(reader, path: str, topic: str | None) -> str:
  """The PointCloud2 topic to read: ``topic``, or the only one."""
  found = reader.topics
  clouds = {k: v.msgcount for k, v in found.items() if v.msgtype == POINTCLOUD2}
  listed = ', '.join(f'{k} ({v} messages)' for k, v in sorted(clouds.items()))
  others = ', '.join(f'{k} ({v.msgtype})' for k, v in sorted(found.items())
                     if k not in clouds)
  if topic is not None:
    if topic in clouds:
      return topic
    what = (f'{topic} is a {found[topic].msgtype}, not a PointCloud2' if topic in found
            else f'no topic {topic}')
    raise DataError(f'{path}: {what}; its PointCloud2 topics: {listed or "none"}')
  if len(clouds) == 1:
    return next(iter(clouds))
  if not clouds:
    raise DataError(f'{path}: no sensor_msgs/PointCloud2 topic (its topics: '
                    f'{others or "none"})')
  raise DataError(f'{path}: {len(clouds)} PointCloud2 topics, {listed}; name one '
                  '(topic=, prepare --topic)')


def count_sweeps(path: str, topic: str | None = None, every: int = 1) -> int:
  """How many sweeps :func:`read_sweeps` yields: from a bag's index (nothing
  decoded); a Velodyne capture is decoded to count its turns; 1 for a
  point file."""
  check_every(every)
  kind = format_of(path)
  if not kind:
    return 1
  if kind == 'velodyne':
    return math.ceil(sum(1 for _ in _velodyne_sweeps(path)) / every)
  reader, _ = _open(path)
  try:
    return math.ceil(reader.topics[_topic(reader, path, topic)].msgcount / every)
  finally:
    reader.close()


def check_every(every):
  """ValueError unless ``every`` is a whole number >= 1."""
  if not isinstance(every, (int, np.integer)) or every < 1:
    raise ValueError(f'every must be a whole number >= 1, got {every!r}')


def read_sweeps(path: str, topic: str | None = None, every: int = 1):
  """The sweeps of the recording or point file ``path``, one after another
  (a generator of :class:`Sweep`; module docstring).

  ``topic``: the PointCloud2 topic of a recording (default its only one);
  ``every``: keep every ``every``-th sweep (0, every, 2 every, ...), to thin
  a 10 Hz recording (a bag's others are not decoded).
  """
  path = os.fspath(path)
  check_every(every)
  if not os.path.exists(path):
    raise DataError(f'{path}: no such file')
  kind = format_of(path)
  if kind in (None, 'velodyne') and topic is not None:
    what = 'a Velodyne capture' if kind else 'a point file of one sweep'
    raise DataError(f'{path}: {what} has no topic')
  if not kind:
    yield Sweep(path, None, points.read_points(path))
    return
  if kind == 'velodyne':
    for index, sweep in enumerate(_velodyne_sweeps(path)):
      if index % every == 0:
        yield sweep
    return
  reader, pointcloud2 = _open(path)
  try:
    name = _topic(reader, path, topic)
    connections = [c for c in reader.connections if c.topic == name]
    index = -1
    try:
      for index, (connection, received, raw) in enumerate(reader.messages(connections)):
        if index % every:
          continue
        source = f'{path}:{name}#{index}'
        try:
          message = reader.deserialize(raw, connection.msgtype)
          fields = _cloud_fields(message, pointcloud2, source)
        except DataError as e:
          yield Sweep(source, int(received), _error=str(e))
          continue
        except Exception as e:  # rosbags' deserialization errors of a damaged message
          yield Sweep(source, int(received), _error=f'{source}: cannot decode the message '
                      f'({type(e).__name__}: {_one_line(e)})')
          continue
        stamp = message.header.stamp
        stamp_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
        yield Sweep(source, stamp_ns or int(received), fields)
    except DataError:
      raise
    except Exception as e:  # a damaged chunk or page: the messages after it are lost
      raise DataError(f'{path}: cannot read on after message {index + 1} of {name} '
                      f'({type(e).__name__}: {_one_line(e)})') from None
  finally:
    reader.close()


def _velodyne_sweeps(path: str):
  """The full turns of a Velodyne capture, as Sweeps stamped with the
  capture (host) time of their last packet; the packets after the last full
  turn are never made a sweep (the decoder's finish())."""
  vd = _velodyne(path)
  config = vd.Config()
  index = 0
  try:
    # As velodyne_decoder.read_pcap: an HDL-64E's model and calibration come
    # from its packets; other models' from each packet's factory bytes.
    config.model, config.calibration = vd.hdl64e.detect_hdl64e(path)
    decoder = vd.StreamDecoder(config)
    for host_stamp, data in vd.util.iter_pcap(path):
      if len(data) != vd.PACKET_SIZE:
        continue  # position and telemetry packets
      result = decoder.decode(host_stamp, data, False)
      if result is None:
        continue
      stamp, cloud = result
      fields = {k: np.ascontiguousarray(cloud[:, i]).astype(dtype)
                for i, (k, dtype) in enumerate(VELODYNE_FIELDS.items())}
      source = f'{path}#{index}'
      index += 1
      yield Sweep(source, int(round(stamp.host * 1e9)), points.check_fields(fields, source))
  except UserError:
    raise
  except Exception as e:  # dpkt's and the decoder's errors of a damaged capture
    raise DataError(f'{path}: cannot decode as a Velodyne capture after sweep {index} '
                    f'({type(e).__name__}: {_one_line(e)})') from None


def _cloud_fields(message, pointcloud2, source: str) -> dict[str, np.ndarray]:
  """The fields of a PointCloud2 message (pointcloud2 reads its layout)."""
  for f in message.fields:
    if f.datatype not in pointcloud2.FIELD_TYPE_TO_NP:
      raise DataError(f'{source}: PointCloud2 field {f.name!r} has datatype {f.datatype}, '
                      f'not one of sensor_msgs/PointField\'s 1..8')
  try:
    data = pointcloud2.read_points(message)
  except (ValueError, TypeError) as e:
    raise DataError(f'{source}: bad PointCloud2 layout ({_one_line(e)}; {message.width} x '
                    f'{message.height} points of {message.point_step} bytes, '
                    f'{len(message.data)} bytes of data)') from None
  fields = {k: np.ascontiguousarray(data[k]) for k in data.dtype.names}
  return points.check_fields(fields, source)
