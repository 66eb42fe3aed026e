"""Ouster recordings: a ``.pcap`` of the sensor's UDP packets with its
metadata ``.json``, read through the optional ``ouster-sdk``
(``pip install 'dusty_jax[ouster]'``).

:func:`read_ouster` gives the points of one sweep as named fields, like
points.read_points (which calls it for a ``.pcap``); :func:`read_metadata`
the unit's own beam calibration, from which a sensor spec is built.

Frames. The SDK's XYZLut returns points in Ouster's *sensor frame*, whose
origin sits below the *lidar frame*'s (36.18 mm on an OS1: the metadata's
lidar_to_sensor_transform) and whose axes are the lidar frame's turned 180
degrees about z. The beam_altitude_angles are elevations seen from the
lidar frame's origin, so the points are returned with the sensor frame's
axes (x away from the connector, as the SDK and Ouster's viewers show them)
and the lidar frame's origin: the SDK's xyz less the transform's translation.
On the OS1-128 sample this puts 99.99% of the points nearest their own
beam's elevation; from the sensor frame's origin 47%.
"""

from __future__ import annotations

import functools
import glob
import json
import os

import numpy as np

from dusty_jax.errors import DataError, UserError

INSTALL = "pip install 'dusty_jax[ouster]'"

# The frame's channel fields (the SDK's names), kept per point in lower case.
# A dual-return profile adds the same names with a '2' for the second return.
CHANNELS = ('RANGE', 'REFLECTIVITY', 'SIGNAL', 'NEAR_IR', 'FLAGS')
SECOND = '2'

MM = 1e-3  # metres per millimetre: the metadata's offsets are in mm.

LUTS_KEPT = 8  # XYZ tables kept, one per metadata file (a few MB each).


def _sdk(path: str):
  """The SDK's open_source and core, or one UserError saying how to install it."""
  try:
    # ouster-sdk is optional (a large download with its own dependencies).
    from ouster.sdk import core, open_source
  except ImportError:
    raise UserError(f'{path}: reading an Ouster recording needs ouster-sdk: {INSTALL}') from None
  return open_source, core


def _one_line(e: Exception) -> str:
  """An SDK error's message on one line (its own span several)."""
  return ' '.join(str(e).split())


def find_metadata(pcap: str) -> str:
  """The metadata json of ``pcap``: the one with its stem beside it, else
  the one json in its folder; DataError naming what was found otherwise."""
  stem = os.path.splitext(pcap)[0]
  if os.path.isfile(stem + '.json'):
    return stem + '.json'
  found = sorted(glob.glob(os.path.join(os.path.dirname(os.path.abspath(pcap)), '*.json')))
  if len(found) == 1:
    return found[0]
  what = f'{len(found)} json files ({", ".join(map(os.path.basename, found))})' if found \
      else 'no json file'
  raise DataError(f'{pcap}: no metadata {os.path.basename(stem)}.json beside it and {what} '
                  'in its folder; give the metadata file')


def _sensor_info(metadata: str, core):
  try:
    with open(metadata) as f:
      text = f.read()
    json.loads(text)
    return core.SensorInfo(text)
  except (OSError, ValueError, RuntimeError) as e:
    raise DataError(f'{metadata}: not an Ouster metadata file ({_one_line(e)})') from None


@functools.lru_cache(maxsize=LUTS_KEPT)
def _calibration(metadata: str, mtime_ns: int, size: int):
  """(SensorInfo, XYZLut) of a metadata file, kept while the file is
  unchanged: the SDK takes ~50 ms to build a 128 x 1024 table, the sweep's
  whole reading budget."""
  _, core = _sdk(metadata)
  info = _sensor_info(metadata, core)
  return info, core.XYZLut(info)


def read_metadata(metadata: str) -> dict:
  """The beam calibration of an Ouster metadata json, as the SDK reads it.

  {'beam_altitude_angles', 'beam_azimuth_angles': (H,) degrees in beam
  order (Ouster's: top beam first), 'lidar_origin_to_beam_origin_mm',
  'beam_to_lidar_transform' and 'lidar_to_sensor_transform': (4, 4) with
  translations in mm, 'columns', 'rings', 'prod_line'}.
  """
  _, core = _sdk(metadata)
  info = _sensor_info(metadata, core)
  return {
      'beam_altitude_angles': np.asarray(info.beam_altitude_angles, np.float64),
      'beam_azimuth_angles': np.asarray(info.beam_azimuth_angles, np.float64),
      'lidar_origin_to_beam_origin_mm': float(info.lidar_origin_to_beam_origin_mm),
      'beam_to_lidar_transform': np.asarray(info.beam_to_lidar_transform, np.float64),
      'lidar_to_sensor_transform': np.asarray(info.lidar_to_sensor_transform, np.float64),
      'columns': int(info.format.columns_per_frame),
      'rings': int(info.format.pixels_per_column),
      'prod_line': info.prod_line,
  }


def frame_fields(frame, info, lut) -> dict[str, np.ndarray]:
  """The returns of one LidarFrame as named fields (module docstring), with
  the SDK's SensorInfo ``info`` of its recording and ``lut``, its XYZLut.

  Pixels of zero range (no return) are dropped. 'ring' is the pixel's row:
  the beam's index in the metadata (0 = top beam); 'intensity' is the
  calibrated reflectivity (the signal where the profile has none). With a
  second return ('RANGE2') its points follow the first ones, 'return_type'
  0 for the first return and 1 for the second; a channel with no second
  twin (NEAR_IR) gives both returns of a pixel its one value.
  """
  origin = np.asarray(info.lidar_to_sensor_transform, np.float64)[:3, 3] * MM
  h, w = frame.h, frame.w
  present = set(frame.fields)
  returns = [''] + ([SECOND] if 'RANGE' + SECOND in present else [])
  parts = []
  for k, tail in enumerate(returns):
    rng = np.asarray(frame.field('RANGE' + tail))
    keep = rng.ravel() > 0
    xyz = lut(rng).reshape(-1, 3)[keep] - origin
    out = {'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2],
           'ring': np.repeat(np.arange(h, dtype=np.uint16), w)[keep]}
    for name in CHANNELS:
      # A channel without a second-return twin (NEAR_IR) is the pixel's own.
      field = name + tail if name + tail in present else name
      if field in present:
        out[name.lower()] = np.asarray(frame.field(field)).ravel()[keep]
    out['intensity'] = out.get('reflectivity', out.get('signal'))
    if out['intensity'] is None:
      del out['intensity']
    out['measurement_id'] = np.tile(np.asarray(frame.measurement_id), h)[keep]
    out['timestamp'] = np.tile(np.asarray(frame.timestamp), h)[keep]
    if len(returns) > 1:
      out['return_type'] = np.full(int(keep.sum()), k, np.uint8)
    parts.append(out)
  if len(parts) == 1:
    return parts[0]
  return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def read_ouster(pcap: str, metadata: str | None = None, frame: int = 0) -> dict[str, np.ndarray]:
  """The returns of sweep ``frame`` of an Ouster ``pcap`` as named fields.

  ``frame`` counts complete sweeps: a partial one (a recording's first or
  last, cut by its start or end) is skipped. ``metadata``: its json
  (default :func:`find_metadata`). Fields: x, y, z
  (metres, float64, the lidar frame's origin: module docstring), ring (the
  beam's row, 0 = top), intensity, the frame's channels in lower case
  (range in mm, reflectivity, signal, near_ir, flags: those the profile
  has), measurement_id and timestamp (ns) of the column, and return_type
  for a dual-return profile. Pixels without a return are left out.
  """
  open_source, _ = _sdk(pcap)
  metadata = metadata or find_metadata(pcap)
  try:
    stat = os.stat(metadata)
  except OSError as e:
    raise DataError(f'{metadata}: cannot read the Ouster metadata ({e.strerror})') from None
  info, lut = _calibration(os.path.abspath(metadata), stat.st_mtime_ns, stat.st_size)
  try:
    source = open_source(pcap, meta=[metadata], sensor_idx=0)
  except Exception as e:  # the SDK's SourceURLException, RuntimeError, ...
    raise DataError(f'{pcap}: cannot open as an Ouster recording with {metadata} '
                    f'({type(e).__name__}: {_one_line(e)})') from None
  complete = partial = 0
  try:
    for frames in source:
      lidar_frame = frames[0]
      if lidar_frame is None or not lidar_frame.complete():
        partial += 1
        continue
      if complete == frame:
        return frame_fields(lidar_frame, info, lut)
      complete += 1
  finally:
    source.close()
  raise DataError(f'{pcap}: no complete sweep {frame}; the recording holds {complete} '
                  f'complete and {partial} partial with {metadata}')
