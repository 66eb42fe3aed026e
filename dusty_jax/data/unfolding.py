"""Point cloud -> range image (numpy; offline data preparation).

Two ways to turn a point cloud into an H x W image:
  * :func:`unfold_scan` follows the sensor's own firing order (KITTI stores
    points ring after ring, each ring sweeping in azimuth), as in the paper;
  * :func:`spherical_projection` bins by elevation angle, for sensors whose
    files have no ring order.
:func:`unfold_rings` places points whose ring id is known (MPO).

:func:`estimate_angles` (or :class:`AngleAccumulator` over many scans)
averages the per-pixel angle table that codec.to_points back-projects with.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from dusty_jax.codec import valid_depth
from dusty_jax.sensor import SensorSpec




@dataclasses.dataclass
class UnfoldReport:
  """What :func:`unfold_scan` found, for the caller to report."""
  rings_found: int
  rings_expected: int
  rows: np.ndarray  # row assigned to each found ring.
  matched_by_elevation: bool

  @property
  def ok(self) -> bool:
    return self.rings_found == self.rings_expected


def azimuth_to_column(azimuth, native_width: int) -> np.ndarray:
  """Native column index of each azimuth (column 0 at the rear, clockwise)."""
  frac = np.mod((1.0 - np.asarray(azimuth) / np.pi) / 2.0, 1.0)
  return np.minimum(np.floor(frac * native_width), native_width - 1).astype(
      np.int64)


def check_points(points: np.ndarray, source: str = 'points') -> np.ndarray:
  """Validates an (N, >=3) float array; names ``source`` in every error."""
  points = np.asarray(points)
  if points.ndim != 2 or points.shape[1] < 3:
    raise ValueError(f'{source}: expected an (N, >=3) array of points, got '
                     f'shape {points.shape}')
  if points.shape[0] == 0:
    raise ValueError(f'{source}: the scan has no points')
  bad = ~np.isfinite(points[:, :3]).all(axis=1)
  if bad.any():
    raise ValueError(f'{source}: {int(bad.sum())} of {len(points)} points '
                     'have NaN or inf coordinates')
  return points


def _scatter_nearest(rows, cols, xyz, keep, sensor, return_xyz):
  """Depth image where the nearest point wins each shared pixel; 0 = empty.

  Only points on kept columns (every ``column_stride``-th native column)
  count. With ``return_xyz`` also the (H, W, 3) points, zeros where empty.
  """
  keep = keep & (cols % sensor.column_stride == 0)
  rows, cols, xyz = rows[keep], cols[keep] // sensor.column_stride, xyz[keep]
  depth = np.linalg.norm(xyz, axis=1)
  order = np.argsort(-depth, kind='stable')  # far first, near written last.
  image = np.zeros(sensor.shape, np.float32)
  image[rows[order], cols[order]] = depth[order]
  if not return_xyz:
    return image
  points = np.zeros(sensor.shape + (3,), np.float32)
  points[rows[order], cols[order]] = xyz[order]
  return image, points


# Within a ring the azimuth only grows (up to jitter far below this).
RING_BREAK_AZIMUTH = np.deg2rad(10.0)


def _split_rings(azimuth: np.ndarray, elevation=None, min_jump=None):
  """Start index of each ring in a sensor-ordered sweep.

  Within a ring the azimuth increases (counter-clockwise, starting straight
  ahead); a new ring begins wherever it falls back by more than
  RING_BREAK_AZIMUTH. Unlike the "quadrant 3 then quadrant 0" rule, this
  also splits rings that have no return straight ahead. With ``elevation``,
  a jump larger than ``min_jump`` radians also starts a ring (for sparse
  rings whose returns do not overlap in azimuth).
  """
  a = np.mod(azimuth, 2 * np.pi)
  brk = np.diff(a) < -RING_BREAK_AZIMUTH
  if elevation is not None:
    brk |= np.abs(np.diff(elevation)) > min_jump
  return np.concatenate([[0], np.flatnonzero(brk) + 1])


def _ring_ids(starts, n):
  ids = np.zeros(n, np.int64)
  ids[starts[1:]] = 1
  return np.cumsum(ids)


def _assign_rows(ring_elevation: np.ndarray, sensor: SensorSpec) -> np.ndarray:
  """Monotone assignment of found rings (top first) to sensor rows.

  Minimises the total |elevation - nominal| subject to rows strictly
  increasing, so a missing ring leaves its row empty instead of shifting the
  rows around it.
  """
  n, h = len(ring_elevation), sensor.height
  nominal = sensor.elevation
  cost = np.abs(ring_elevation[:, None] - nominal[None, :])  # (n, h)
  inf = np.inf
  # best[i, j]: min cost placing rings 0..i with ring i at row j.
  best = np.full((n, h), inf)
  arg = np.zeros((n, h), np.int64)
  best[0] = cost[0]
  for i in range(1, n):
    prefix = np.minimum.accumulate(best[i - 1])
    prefix_arg = np.zeros(h, np.int64)
    cur = 0
    for j in range(h):
      if best[i - 1, j] <= best[i - 1, cur]:
        cur = j
      prefix_arg[j] = cur
    best[i, 1:] = prefix[:-1] + cost[i, 1:]
    arg[i, 1:] = prefix_arg[:-1]
  rows = np.zeros(n, np.int64)
  rows[-1] = int(np.argmin(best[-1]))
  for i in range(n - 1, 0, -1):
    rows[i - 1] = arg[i, rows[i]]
  return rows


def unfold_scan(points: np.ndarray, sensor: SensorSpec, source: str = 'scan',
                return_xyz: bool = False):
  """Unfolds a sensor-ordered scan (KITTI velodyne) into an (H, W) depth image.

  Args:
    points: (N, >=3) x, y, z[, reflectance], stored ring after ring, top
      beam first, each ring sweeping counter-clockwise from straight ahead.
    sensor: the sensor spec (H rings, native and kept columns).
    source: a name for error messages (the file path).

  Returns:
    depth: (H, W) float32 metric range, 0 where no point landed.
    xyz: (H, W, 3) points of the winning returns, only with ``return_xyz``.
    report: rings found versus expected. When the counts differ, rings are
      matched to rows by their median elevation (so an empty ring leaves an
      empty row instead of shifting every row above it) and a warning names
      ``source``.
  """
  points = check_points(points, source)
  xyz = points[:, :3].astype(np.float64)
  azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
  starts = _split_rings(azimuth)
  n_rings = len(starts)
  ring_id = _ring_ids(starts, len(xyz))

  if n_rings == sensor.height:
    rows_of_ring = np.arange(n_rings)
    matched = False
  else:
    elev = np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))
    if n_rings < sensor.height and sensor.height > 1:
      # Rings may be missing or merged: also split on elevation jumps.
      spacing = np.min(np.abs(np.diff(sensor.elevation)))
      starts = _split_rings(azimuth, elev, 0.6 * spacing)
      n_rings = len(starts)
      ring_id = _ring_ids(starts, len(xyz))
    if n_rings > sensor.height:
      raise ValueError(
          f'{source}: found {n_rings} rings but sensor {sensor.name!r} has '
          f'{sensor.height}; is this the right sensor, and is the file in '
          'sensor order?')
    ring_elev = np.array(
        [np.median(elev[ring_id == r]) for r in range(n_rings)])
    rows_of_ring = _assign_rows(ring_elev, sensor)
    matched = True
    warnings.warn(
        f'{source}: found {n_rings} rings, sensor {sensor.name!r} has '
        f'{sensor.height}; rings matched to rows by elevation, rows '
        f'{sorted(set(range(sensor.height)) - set(rows_of_ring.tolist()))} '
        'left empty', stacklevel=2)

  rows = rows_of_ring[ring_id]
  cols = azimuth_to_column(azimuth, sensor.native_width)
  out = _scatter_nearest(rows, cols, xyz, np.ones(len(xyz), bool), sensor,
                         return_xyz)
  report = UnfoldReport(n_rings, sensor.height, rows_of_ring, matched)
  return (*out, report) if return_xyz else (out, report)


def unfold_rings(points: np.ndarray, ring: np.ndarray, sensor: SensorSpec,
                 source: str = 'scan', bottom_first: bool = True,
                 return_xyz: bool = False):
  """(H, W) depth image from points with known laser ring ids (MPO).

  ``ring`` ids run 0..H-1; with ``bottom_first`` (the Velodyne driver's
  convention) ring 0 is the lowest beam and lands in the last row.
  """
  points = check_points(points, source)
  ring = np.asarray(ring).astype(np.int64)
  if ring.shape != (len(points),):
    raise ValueError(f'{source}: {len(ring)} ring ids for {len(points)} points')
  if ring.min() < 0 or ring.max() >= sensor.height:
    raise ValueError(f'{source}: ring ids span {ring.min()}..{ring.max()}, '
                     f'sensor {sensor.name!r} has rings 0..{sensor.height - 1}')
  xyz = points[:, :3].astype(np.float64)
  rows = sensor.height - 1 - ring if bottom_first else ring
  cols = azimuth_to_column(np.arctan2(xyz[:, 1], xyz[:, 0]), sensor.native_width)
  return _scatter_nearest(rows, cols, xyz, np.ones(len(xyz), bool), sensor,
                          return_xyz)


def spherical_projection(points: np.ndarray, sensor: SensorSpec,
                         source: str = 'scan', return_xyz: bool = False):
  """(H, W) depth image binning points by elevation (nearest nominal beam).

  For sensors without ring order. Points beyond half a beam spacing above the
  top beam or below the bottom beam are discarded.
  """
  points = check_points(points, source)
  xyz = points[:, :3].astype(np.float64)
  elev = np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))
  nominal = sensor.elevation  # decreasing
  rows = np.argmin(np.abs(elev[:, None] - nominal[None, :]), axis=1)
  spacing = np.abs(np.diff(nominal)) if sensor.height > 1 else np.array([1.0])
  margin = 0.5 * np.concatenate([[spacing[0]], spacing, [spacing[-1]]])
  inside = (elev <= nominal[0] + margin[0]) & (elev >= nominal[-1] - margin[-1])
  cols = azimuth_to_column(np.arctan2(xyz[:, 1], xyz[:, 0]), sensor.native_width)
  return _scatter_nearest(rows, cols, xyz, inside, sensor, return_xyz)


# ----------------------------------------------------------------------------




class AngleAccumulator:
  """Running per-pixel sums for :func:`estimate_angles` over many scans."""

  def __init__(self, sensor: SensorSpec):
    self.sensor = sensor
    shape = sensor.shape
    self.count = np.zeros(shape, np.int64)
    self.elevation = np.zeros(shape, np.float64)
    self.az_cos = np.zeros(shape, np.float64)
    self.az_sin = np.zeros(shape, np.float64)

  def add(self, xyz_image: np.ndarray):
    """Adds one (H, W, 3) image of points (zeros where empty)."""
    xyz = np.asarray(xyz_image, np.float64)
    depth = np.linalg.norm(xyz, axis=-1)
    valid = np.asarray(valid_depth(depth, self.sensor))
    el = np.arctan2(xyz[..., 2], np.hypot(xyz[..., 0], xyz[..., 1]))
    az = np.arctan2(xyz[..., 1], xyz[..., 0])
    self.count += valid
    self.elevation += np.where(valid, el, 0)
    self.az_cos += np.where(valid, np.cos(az), 0)
    self.az_sin += np.where(valid, np.sin(az), 0)

  def result(self) -> np.ndarray:
    """(2, H, W) float32: mean elevation, circular-mean azimuth per pixel.

    Pixels never valid take their row's mean elevation and their column's
    mean azimuth; rows or columns never valid at all take the sensor's
    nominal angles.
    """
    nominal = self.sensor.nominal_angles().astype(np.float64)
    seen = self.count > 0
    el = np.where(seen, self.elevation / np.maximum(self.count, 1), np.nan)
    az = np.where(seen, np.arctan2(self.az_sin, self.az_cos), np.nan)
    with warnings.catch_warnings():
      warnings.simplefilter('ignore', RuntimeWarning)
      row_el = np.nanmean(el, axis=1)
    row_el = np.where(np.isfinite(row_el), row_el, nominal[0, :, 0])
    col_az = np.arctan2(self.az_sin.sum(0), self.az_cos.sum(0))
    col_az = np.where(seen.any(0), col_az, nominal[1, 0, :])
    el = np.where(seen, el, row_el[:, None])
    az = np.where(seen, az, col_az[None, :])
    return np.stack([el, az]).astype(np.float32)


def estimate_angles(xyz_images, sensor: SensorSpec) -> np.ndarray:
  """Per-pixel angle table from an iterable of (H, W, 3) point images."""
  acc = AngleAccumulator(sensor)
  for img in xyz_images:
    acc.add(img)
  return acc.result()
