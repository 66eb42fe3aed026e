"""Reads TensorBoard event files back without the writer: TFRecord framing by
hand, each record decoded as a ``tensorflow.Event`` proto."""

import struct

from tensorboardX.proto import event_pb2
from tensorboardX.record_writer import masked_crc32c


def read_events(path):
  """All events in the file, checking each record's length and data CRC."""
  with open(path, 'rb') as f:
    data = f.read()
  events, i = [], 0
  while i < len(data):
    header = data[i:i + 8]
    (n,) = struct.unpack('<Q', header)
    assert struct.unpack('<I', data[i + 8:i + 12])[0] == masked_crc32c(header)
    payload = data[i + 12:i + 12 + n]
    assert len(payload) == n, f'{path}: record cut short at byte {i}'
    assert struct.unpack('<I', data[i + 12 + n:i + 16 + n])[0] == masked_crc32c(payload)
    event = event_pb2.Event()
    event.ParseFromString(payload)
    events.append(event)
    i += 16 + n
  return events


def scalars(events):
  """[(step, tag, value)] of every scalar summary, in file order."""
  return [(e.step, v.tag, v.simple_value)
          for e in events if e.HasField('summary') for v in e.summary.value]
