"""LiDAR sensor spec: the single source of every shape in dusty_jax.

A scan is a cylindrical range image of ``rings x columns`` pixels. The data
readers, the networks and the metrics all derive H and W from a
:class:`SensorSpec`; supporting a new LiDAR means adding a preset here and
nothing else.

Angle conventions (shared with the KITTI scan order):
  * elevation: degrees above the horizontal plane, row 0 is the top beam;
  * azimuth: ``atan2(y, x)``, x forward, y left. Column 0 starts at the rear
    (azimuth +pi) and columns advance clockwise seen from above, so the
    image centre looks straight ahead.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class SensorSpec:
  """An immutable description of a spinning multi-beam LiDAR.

  Attributes:
    name: preset name.
    elevation_deg: per-ring nominal elevation in degrees, top beam first.
      Its length is the number of rings H.
    width: columns W of the range image the model sees.
    native_width: columns per revolution before subsampling; must be a
      multiple of ``width`` (every ``native_width // width``-th column kept).
    min_depth: nearest valid range in metres (exclusive).
    max_depth: farthest valid range in metres (exclusive).
    mount_height: sensor height above the ground in metres (for simulation).
  """

  name: str
  elevation_deg: tuple[float, ...]
  width: int
  native_width: int
  min_depth: float = 0.9
  max_depth: float = 120.0
  mount_height: float = 1.73

  def to_dict(self) -> dict:
    """JSON-ready fields (``elevation_deg`` as a list); :meth:`from_dict`
    reads them back."""
    d = dataclasses.asdict(self)
    d['elevation_deg'] = list(d['elevation_deg'])
    return d

  @classmethod
  def from_dict(cls, d: dict) -> 'SensorSpec':
    return cls(**dict(d, elevation_deg=tuple(d['elevation_deg'])))

  def __post_init__(self):
    if len(self.elevation_deg) < 1:
      raise ValueError(f'sensor {self.name!r}: no rings given')
    if self.width < 1 or self.native_width % self.width:
      raise ValueError(
          f'sensor {self.name!r}: native_width={self.native_width} is not a '
          f'multiple of width={self.width}')
    if not 0 < self.min_depth < self.max_depth:
      raise ValueError(
          f'sensor {self.name!r}: need 0 < min_depth < max_depth, got '
          f'{self.min_depth}, {self.max_depth}')
    if any(np.diff(self.elevation_deg) >= 0):
      raise ValueError(
          f'sensor {self.name!r}: elevation_deg must decrease strictly '
          '(top beam first)')

  @property
  def height(self) -> int:
    return len(self.elevation_deg)

  @property
  def shape(self) -> tuple[int, int]:
    return (self.height, self.width)

  @property
  def column_stride(self) -> int:
    return self.native_width // self.width

  @property
  def elevation(self) -> np.ndarray:
    """Per-ring elevation in radians, shape (H,)."""
    return np.deg2rad(np.asarray(self.elevation_deg, np.float64))

  def column_azimuth(self, native: bool = False) -> np.ndarray:
    """Azimuth (radians) at the centre of each kept column, shape (W,)."""
    n = self.native_width
    cols = np.arange(n) if native else np.arange(self.width) * self.column_stride
    frac = (cols + 0.5) / n
    return np.pi * (1.0 - 2.0 * frac)

  def nominal_angles(self) -> np.ndarray:
    """Angle table from the spec alone, shape (2, H, W): elevation, azimuth."""
    el = np.broadcast_to(self.elevation[:, None], self.shape)
    az = np.broadcast_to(self.column_azimuth()[None, :], self.shape)
    return np.stack([el, az]).astype(np.float32)

  def with_width(self, width: int) -> 'SensorSpec':
    return dataclasses.replace(self, width=width)


def _hdl64e_elevations() -> tuple[float, ...]:
  # Upper block: 32 lasers about 1/3 degree apart; lower block: 32 lasers
  # about 1/2 degree apart (Velodyne HDL-64E S2 datasheet, +2 to -24.9 deg).
  upper = np.linspace(2.0, -8.33, 32)
  lower = np.linspace(-8.83, -24.9, 32)
  return tuple(float(a) for a in np.concatenate([upper, lower]))


def _hdl32e_elevations() -> tuple[float, ...]:
  # 32 lasers uniformly spaced from +10.67 to -30.67 degrees.
  return tuple(float(a) for a in np.linspace(10.67, -30.67, 32))


PRESETS: dict[str, SensorSpec] = {
    'kitti': SensorSpec('kitti', _hdl64e_elevations(), width=256,
                        native_width=2048),
    'mpo': SensorSpec('mpo', _hdl32e_elevations(), width=256,
                      native_width=2048),
}


def get_sensor(name: str) -> SensorSpec:
  """Returns a preset by name ('kitti' for HDL-64E, 'mpo' for HDL-32E)."""
  try:
    return PRESETS[name]
  except KeyError:
    raise ValueError(
        f'unknown sensor {name!r}; known presets: {sorted(PRESETS)}') from None


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
  """Builds a SensorSpec from a config's ``sensor`` ConfigDict."""
  if cfg.get('preset'):
    spec = get_sensor(cfg.preset)
  else:
    spec = tiny_sensor(cfg.height, cfg.width)
  if cfg.get('width') and cfg.width != spec.width:
    spec = dataclasses.replace(spec, width=cfg.width,
                               native_width=cfg.width * spec.column_stride)
  return spec
