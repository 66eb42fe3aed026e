"""LiDAR sensor spec: the single source of every shape in dusty_jax.

A scan is a cylindrical range image of ``rings x columns`` pixels. The data
readers, the networks and the metrics all derive H and W from a
:class:`SensorSpec`. A sensor is data: a preset by name (:data:`PRESETS`), or
a JSON file of :meth:`SensorSpec.to_dict`'s fields read by :func:`load`
(``--config.sensor.file=PATH``; ``prepare --sensor PATH``), or one estimated
from a recording (data/estimate.py; ``prepare --sensor auto``).

Angle conventions (shared with the KITTI scan order):
  * elevation: degrees above the horizontal plane, row 0 is the top beam;
  * azimuth: ``atan2(y, x)``, x forward, y left. Column 0 starts at the rear
    (azimuth +pi) and columns advance clockwise seen from above, so the
    image centre looks straight ahead.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os

import numpy as np

from dusty_jax import files
from dusty_jax.errors import DataError


@dataclasses.dataclass(frozen=True)
class SensorSpec:
  """An immutable description of a spinning multi-beam LiDAR.

  Attributes:
    name: preset or sensor name.
    elevation_deg: per-ring nominal elevation in degrees, top beam first.
      Its length is the number of rings H.
    width: columns W of the range image the model sees.
    native_width: firings per revolution of each beam (>= ``width``). Each
      image column keeps the returns of one native column's worth of azimuth
      at its start (:meth:`column_of`): with ``native_width`` a multiple of
      ``width``, every ``native_width // width``-th firing, as the authors
      subsample KITTI.
    min_depth: nearest valid range in metres (exclusive).
    max_depth: farthest valid range in metres (exclusive).
    mount_height: sensor height above the ground in metres (for simulation).
    azimuth_offset_deg: optional per-beam azimuth offset in degrees (a beam
      fires this far counter-clockwise of its column's encoder angle, as
      Ouster's ``beam_azimuth_angles``); () for none.
    vertical_offset_m: optional per-beam offset ``b`` in metres of the
      elevation model ``sin(elevation) = sin(elevation_deg) + b / range``: a
      beam whose origin lies off the sensor's origin (Ouster's beams start
      10-30 mm off its axis) sees near points off its nominal angle; () for
      none.
  """

  name: str
  elevation_deg: tuple[float, ...]
  width: int
  native_width: int
  min_depth: float = 0.9
  max_depth: float = 120.0
  mount_height: float = 1.73
  azimuth_offset_deg: tuple[float, ...] = ()
  vertical_offset_m: tuple[float, ...] = ()

  def to_dict(self) -> dict:
    """JSON-ready fields (tuples as lists); :meth:`from_dict` reads them back."""
    d = dataclasses.asdict(self)
    for k in PER_BEAM:
      d[k] = list(d[k])
    return d

  @classmethod
  def from_dict(cls, d: dict, source: str = 'sensor spec') -> 'SensorSpec':
    """The spec of :meth:`to_dict`'s fields; ``source`` (a path) names it in
    errors. Fields a spec may omit take their defaults."""
    if not isinstance(d, dict):
      raise DataError(f'{source}: a sensor spec is a JSON object of fields, got '
                      f'{type(d).__name__}')
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - set(fields))
    missing = [k for k in ('name', 'elevation_deg', 'width', 'native_width')
               if k not in d]
    if unknown or missing:
      raise DataError(f'{source}: ' + '; '.join(
          ([f'unknown fields {unknown}'] if unknown else []) +
          ([f'missing fields {missing}'] if missing else [])) +
          f' (a sensor spec has {sorted(fields)})')
    kw = dict(d)
    for k in PER_BEAM:
      if k in kw:
        kw[k] = _numbers(k, kw[k], source)
    for k in ('width', 'native_width', 'min_depth', 'max_depth', 'mount_height'):
      if k in kw:
        kw[k] = _number(k, kw[k], source, whole=k.endswith('width'))
    if not isinstance(kw['name'], str):
      raise DataError(f'{source}: name must be a string, got {_shown(kw["name"])}')
    try:
      return cls(**kw)
    except ValueError as e:
      raise DataError(f'{source}: {e}') from None

  def __post_init__(self):
    where = f'sensor {self.name!r}'
    el = np.asarray(self.elevation_deg, np.float64)
    if el.ndim != 1 or len(el) < 1:
      raise ValueError(f'{where}: no rings given')
    if len(el) > MAX_BEAMS:
      raise ValueError(f'{where}: {len(el):,} beams; a spec holds at most {MAX_BEAMS:,} '
                       '(a ring id is 16 bits in the drivers\' formats)')
    if not (np.isfinite(el).all() and (np.abs(el) < 90).all()):
      raise ValueError(f'{where}: elevation_deg must be finite and inside '
                       f'(-90, 90) degrees, got [{el.min()}, {el.max()}]')
    if any(np.diff(el) >= 0):
      raise ValueError(f'{where}: elevation_deg must decrease strictly '
                       '(top beam first)')
    if self.width < 1 or self.native_width < self.width:
      raise ValueError(
          f'{where}: need 1 <= width <= native_width, got width={self.width}, '
          f'native_width={self.native_width}')
    if not (math.isfinite(self.min_depth) and math.isfinite(self.max_depth)
            and 0 < self.min_depth < self.max_depth):
      raise ValueError(
          f'{where}: need 0 < min_depth < max_depth (finite), got '
          f'{self.min_depth}, {self.max_depth}')
    if not math.isfinite(self.mount_height):
      raise ValueError(f'{where}: mount_height must be finite')
    for k in PER_BEAM:
      v = np.asarray(getattr(self, k), np.float64)
      if len(v) not in (0, len(el)) or not np.isfinite(v).all():
        raise ValueError(f'{where}: {k} needs one finite value per ring '
                         f'({len(el)}) or none, got {len(v)}')

  @property
  def height(self) -> int:
    return len(self.elevation_deg)

  @property
  def shape(self) -> tuple[int, int]:
    return (self.height, self.width)

  @property
  def column_stride(self) -> int | None:
    """Native columns per image column where ``native_width`` is a multiple
    of ``width`` (the kept one is the first); None otherwise."""
    s, r = divmod(self.native_width, self.width)
    return None if r else s

  @property
  def elevation(self) -> np.ndarray:
    """Per-ring elevation in radians, shape (H,)."""
    return np.deg2rad(np.asarray(self.elevation_deg, np.float64))

  @property
  def azimuth_offset(self) -> np.ndarray:
    """Per-ring azimuth offset in radians, shape (H,) (zeros if none)."""
    return np.deg2rad(np.asarray(self.azimuth_offset_deg or
                                 (0.0,) * self.height, np.float64))

  @property
  def vertical_offset(self) -> np.ndarray:
    """Per-ring ``b`` of ``sin(el) = sin(elevation) + b / range``, (H,)."""
    return np.asarray(self.vertical_offset_m or (0.0,) * self.height, np.float64)

  def column_azimuth(self, native: bool = False) -> np.ndarray:
    """Azimuth (radians) at the centre of each kept column, shape (W,)."""
    n = self.native_width
    if native:
      cols = np.arange(n)
    elif self.column_stride:
      cols = np.arange(self.width) * self.column_stride
    else:
      cols = np.arange(self.width) * (n / self.width)
    frac = (cols + 0.5) / n
    return np.pi * (1.0 - 2.0 * frac)

  def column_of(self, azimuth) -> tuple[np.ndarray, np.ndarray]:
    """(image column, kept) of each azimuth in radians: a return is kept when
    it lies in the first native column's worth of azimuth of its image column
    (every ``column_stride``-th firing where the widths divide)."""
    n, w = self.native_width, self.width
    frac = np.mod((1.0 - np.asarray(azimuth, np.float64) / np.pi) / 2.0, 1.0)
    if self.column_stride:
      native = np.minimum(np.floor(frac * n), n - 1).astype(np.int64)
      col, rest = np.divmod(native, self.column_stride)
      return col, rest == 0
    u = frac * w
    col = np.minimum(np.floor(u), w - 1).astype(np.int64)
    return col, (u - col) < w / n

  def nominal_angles(self) -> np.ndarray:
    """Angle table from the spec alone, shape (2, H, W): elevation, azimuth
    (each beam's azimuth offset added)."""
    el = np.broadcast_to(self.elevation[:, None], self.shape)
    az = self.column_azimuth()[None, :] + self.azimuth_offset[:, None]
    az = np.broadcast_to(np.angle(np.exp(1j * az)) if self.azimuth_offset_deg
                         else az, self.shape)
    return np.stack([el, az]).astype(np.float32)

  def with_width(self, width: int) -> 'SensorSpec':
    return dataclasses.replace(self, width=width)


PER_BEAM = ('elevation_deg', 'azimuth_offset_deg', 'vertical_offset_m')
# No spinning LiDAR numbers more beams than a 16-bit ring id holds (the ring
# field of Velodyne's, Ouster's and Hesai's point clouds): a larger spec is a
# mistake, refused before its images are allocated.
MAX_BEAMS = 2 ** 16
# What a prepared dataset's depths depend on, in the order a difference is
# named (:func:`first_difference`): its rows, its columns, its range.
DATA_FIELDS = ('elevation_deg', 'vertical_offset_m', 'azimuth_offset_deg', 'width',
               'native_width', 'min_depth', 'max_depth')


def _shown(v) -> str:
  """A spec file's value as JSON shows it (a string quoted, true lowercase)."""
  text = json.dumps(v) if isinstance(v, (str, bool, int, float)) or v is None else repr(v)
  return text if len(text) <= 40 else text[:37] + '...'


def _number(field: str, v, source: str, whole: bool = False):
  """A spec file's number (an int where ``whole``); DataError naming
  ``field`` for a string, a boolean or a fraction."""
  if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
    raise DataError(f'{source}: {field} must be {"an integer" if whole else "a number"}, '
                    f'got {_shown(v)}')
  if whole:
    if not math.isfinite(v) or v != int(v):
      raise DataError(f'{source}: {field} must be an integer, got {_shown(v)}')
    return int(v)
  return float(v)


def _numbers(field: str, v, source: str) -> tuple[float, ...]:
  """A spec file's per-beam list; DataError naming ``field`` for anything
  but a list of numbers (a string, a number, a list holding either), or one
  longer than MAX_BEAMS (refused before it is read)."""
  if not isinstance(v, (list, tuple, np.ndarray)) or np.ndim(v) != 1:
    raise DataError(f'{source}: {field} must be a list of numbers, one per beam, top '
                    f'beam first, got {_shown(v)}')
  if len(v) > MAX_BEAMS:
    raise DataError(f'{source}: {field} lists {len(v):,} beams; a spec holds at most '
                    f'{MAX_BEAMS:,} (a ring id is 16 bits in the drivers\' formats)')
  bad = [a for a in v if isinstance(a, bool) or
         not isinstance(a, (int, float, np.integer, np.floating))]
  if bad:
    raise DataError(f'{source}: {field} must be a list of numbers, one per beam, top '
                    f'beam first; it holds {_shown(bad[0])}')
  return tuple(float(a) for a in v)


def first_difference(a: SensorSpec, b: SensorSpec, labels=('a', 'b'),
                     fields=DATA_FIELDS) -> str | None:
  """The first of ``fields`` in which two specs differ, as ``'FIELD: LABEL_A
  value, LABEL_B value'`` (a per-beam field: its beam count, else its first
  differing beam); None where they agree."""
  la, lb = labels
  for f in fields:
    x, y = getattr(a, f), getattr(b, f)
    if f in PER_BEAM and len(x) != len(y):
      return f'{f}: {la} {len(x)} beams, {lb} {len(y)}'
    if f in PER_BEAM:
      i = next((i for i, (p, q) in enumerate(zip(x, y)) if p != q), None)
      if i is not None:
        return f'{f}[{i}]: {la} {x[i]!r}, {lb} {y[i]!r}'
    elif x != y:
      return f'{f}: {la} {x!r}, {lb} {y!r}'
  return None


def load(path: str) -> SensorSpec:
  """The sensor spec in a JSON file of :meth:`SensorSpec.to_dict`'s fields;
  DataError naming the file and the field for anything else."""
  try:
    with open(path) as f:
      d = json.load(f)
  except OSError as e:
    raise DataError(f'{path}: cannot read the sensor spec ({e.strerror})') from None
  except (json.JSONDecodeError, UnicodeDecodeError) as e:
    raise DataError(f'{path}: not a JSON sensor spec ({e})') from None
  try:
    return SensorSpec.from_dict(d, source=path)
  except DataError:
    raise
  except ValueError as e:  # __post_init__'s checks
    raise DataError(f'{path}: {e}') from None


def save(spec: SensorSpec, path: str):
  """Writes ``spec`` as a JSON file :func:`load` reads (atomically)."""
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  with files.atomic_write(path) as f:
    json.dump(spec.to_dict(), f, indent=1)
    f.write('\n')


def from_ouster_metadata(path: str, width: int | None = None) -> SensorSpec:
  """A unit's own calibration from an Ouster metadata JSON: its
  ``beam_altitude_angles``, ``beam_azimuth_angles``, beam-origin offset and
  columns per frame, for points in the lidar frame (data/ouster.py).

  Ouster's software manual computes a return at range r as ``r' = r - n``,
  ``z = r' sin(phi)``, horizontally ``r' cos(phi) + n`` (n the beam-origin
  offset), at azimuth ``encoder - beam_azimuth``; so the elevation model's
  ``b = -n sin(phi) cos(phi)`` to first order in n / r, and a beam's
  azimuth offset is minus its ``beam_azimuth_angles``.
  """
  try:
    with open(path) as f:
      meta = json.load(f)
  except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
    raise DataError(f'{path}: cannot read the Ouster metadata ({e})') from None
  intr = meta.get('beam_intrinsics', meta)
  fmt = meta.get('data_format', {})
  try:
    alt = np.asarray(intr['beam_altitude_angles'], np.float64)
    azi = np.asarray(intr['beam_azimuth_angles'], np.float64)
    if 'lidar_origin_to_beam_origin_mm' in intr:
      n = float(intr['lidar_origin_to_beam_origin_mm'])
    else:
      n = float(np.asarray(intr['beam_to_lidar_transform'], np.float64).reshape(4, 4)[0, 3])
    columns = int(fmt.get('columns_per_frame') or
                  str(meta['lidar_mode']).split('x')[0])
  except (KeyError, TypeError, ValueError) as e:
    raise DataError(f'{path}: not an Ouster metadata file (no {e})') from None
  if not len(alt) or len(azi) != len(alt):
    raise DataError(f'{path}: {len(alt)} beam altitudes and {len(azi)} azimuths')
  phi = np.deg2rad(alt)
  b = -(n / 1000.0) * np.sin(phi) * np.cos(phi)
  name = str(meta.get('prod_line') or 'ouster').lower()
  return SensorSpec(name, tuple(alt.tolist()), width=width or columns,
                    native_width=columns, min_depth=0.3, max_depth=120.0,
                    azimuth_offset_deg=tuple((-azi).tolist()),
                    vertical_offset_m=tuple(b.tolist()))


def _hdl64e_elevations() -> tuple[float, ...]:
  # Upper block: 32 lasers about 1/3 degree apart; lower block: 32 lasers
  # about 1/2 degree apart (Velodyne HDL-64E S2 datasheet, +2 to -24.9 deg).
  # The form the KITTI preset has always used (its lower block spans to
  # -24.9 degrees, as KITTI's scans do).
  upper = np.linspace(2.0, -8.33, 32)
  lower = np.linspace(-8.83, -24.9, 32)
  return tuple(float(a) for a in np.concatenate([upper, lower]))


def _hdl32e_elevations() -> tuple[float, ...]:
  # 32 lasers uniformly spaced from +10.67 to -30.67 degrees.
  return tuple(float(a) for a in np.linspace(10.67, -30.67, 32))


def _degrees(values) -> tuple[float, ...]:
  return tuple(round(float(a), 6) for a in values)


PRESETS: dict[str, SensorSpec] = {
    # The paper's two sensors, as the authors' code shapes them.
    'kitti': SensorSpec('kitti', _hdl64e_elevations(), width=256,
                        native_width=2048),
    'mpo': SensorSpec('mpo', _hdl32e_elevations(), width=256,
                      native_width=2048),
    # Velodyne VLP-16 User Manual (63-9243 Rev. D), Table 9-1: 16 lasers from
    # -15 to +15 degrees, 2 degrees apart; 0.2 degree azimuth resolution at
    # 600 RPM (1800 firings per revolution); range up to 100 m.
    'vlp16': SensorSpec('vlp16', _degrees(np.arange(15, -16, -2)), width=1024,
                        native_width=1800, min_depth=0.5, max_depth=100.0),
    # Velodyne HDL-32E User's Manual (63-9113 Rev. J): 32 lasers from +10.67
    # to -30.67 degrees (1.33 apart); one firing cycle per 46.08 us, so 1085
    # per revolution at nuScenes' 20 Hz (Caesar et al., CVPR 2020, Table 1);
    # range up to 100 m; nuScenes mounts it about 1.84 m above the ground.
    'hdl32e': SensorSpec('hdl32e', _degrees(np.linspace(10.67, -30.67, 32)),
                         width=1024, native_width=1085, min_depth=1.0,
                         max_depth=100.0, mount_height=1.84),
    # Velodyne HDL-64E S2 datasheet (97-0038 Rev. D) and user's manual:
    # vertical field of view +2 to -24.8 degrees, the upper block of 32 lasers
    # about 1/3 degree apart down to -8.33, the lower block 1/2 degree apart
    # from -8.83; 0.1728 degree azimuth resolution at 600 RPM (2083 firings).
    'hdl64e': SensorSpec('hdl64e', _degrees(np.concatenate([
        np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.33, 32)])),
                         width=1024, native_width=2083, min_depth=0.9,
                         max_depth=120.0),
    # Ouster OS1 datasheet (rev 7, OS1 gen 2): 45 degree vertical field of
    # view (+22.5 to -22.5), beams uniformly spaced; 512, 1024 or 2048
    # columns per revolution (1024 at 10 Hz here); range 0.3 to 120 m. A
    # unit's own angles and beam offsets: from_ouster_metadata().
    'os1-64': SensorSpec('os1-64', _degrees(np.linspace(22.5, -22.5, 64)),
                         width=1024, native_width=1024, min_depth=0.3,
                         max_depth=120.0),
    'os1-128': SensorSpec('os1-128', _degrees(np.linspace(22.5, -22.5, 128)),
                          width=1024, native_width=1024, min_depth=0.3,
                          max_depth=120.0),
}


def get_sensor(name: str) -> SensorSpec:
  """A preset by name (:data:`PRESETS`), or a spec file's path (:func:`load`).

  A name becomes a spec here, where a program starts (a command's flags, the
  trainer's config: :func:`from_config`); everything below takes the spec
  (:func:`check_spec`)."""
  if name in PRESETS:
    return PRESETS[name]
  if name.endswith('.json') or os.path.sep in name:
    return load(name)
  raise ValueError(
      f'unknown sensor {name!r}; known presets: {sorted(PRESETS)}, or the path '
      'of a sensor spec JSON file')


def check_spec(sensor, what: str = 'sensor') -> SensorSpec:
  """``sensor`` as it is, if a SensorSpec; else a TypeError saying how to
  make one (a name is resolved where a program starts: :func:`get_sensor`)."""
  if not isinstance(sensor, SensorSpec):
    got = f'{type(sensor).__name__} {sensor!r}' if isinstance(sensor, str) else \
        type(sensor).__name__
    raise TypeError(f'{what}: expected a SensorSpec (params.sensor, or '
                    f"dusty_jax.get_sensor('kitti') for a preset or a spec file), got {got}")
  return sensor


def tiny_sensor(height: int = 16, width: int = 64) -> SensorSpec:
  """A small sensor for tests and smoke runs: the KITTI field of view."""
  el = np.linspace(2.0, -24.9, height)
  return SensorSpec(f'tiny{height}x{width}', tuple(float(a) for a in el),
                    width=width, native_width=width * 8)


def check_angles(angles, shape, source: str = '', finite: bool = False):
  """The one check of a per-pixel (2, H, W) elevation/azimuth table against
  the scans' (H, W) ``shape``; ``finite``: also refuse NaN and inf (only for
  tables read from files: a table inside a jitted function is not concrete).
  ``source`` prefixes the message (a path). Raises ValueError."""
  want = (2,) + tuple(shape)
  got = tuple(np.shape(angles))
  if got != want or (finite and not np.isfinite(angles).all()):
    raise ValueError(f'{source}angles of shape {got}, expected '
                     f'{"finite " if finite else ""}{want}')


def from_config(cfg) -> SensorSpec:
  """The SensorSpec a config's ``sensor`` ConfigDict names: its ``file``,
  else its ``preset``, else a tiny sensor of ``height x width``; a nonzero
  ``width`` then sets the columns. Read once, where training starts
  (configs.validate); a run records the spec in its generator.json."""
  if cfg.get('file'):
    spec = load(os.path.expanduser(cfg.file))
  elif cfg.get('preset'):
    spec = get_sensor(cfg.preset)
  else:
    return tiny_sensor(cfg.height, cfg.width)
  if cfg.get('width') and cfg.width != spec.width:
    spec = with_columns(spec, cfg.width)
  return spec


def source_of(cfg) -> str:
  """Where :func:`from_config` takes a config's spec from, in words."""
  if cfg.get('file'):
    return f'sensor.file={cfg["file"]}'
  if cfg.get('preset'):
    return f'preset {cfg["preset"]!r}'
  return f'a tiny sensor of {cfg.get("height")}x{cfg.get("width")}'


def with_columns(spec: SensorSpec, width: int) -> SensorSpec:
  """``spec`` seen at ``width`` columns: where the widths divide, the same
  firing stride (as a KITTI scan at 512 columns keeps every 8th of 4096);
  else the sensor's own firings, of which ``width`` must not ask more."""
  if spec.column_stride:
    return dataclasses.replace(spec, width=width,
                               native_width=width * spec.column_stride)
  return dataclasses.replace(spec, width=width)
