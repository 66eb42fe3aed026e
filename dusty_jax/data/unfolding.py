"""Point cloud -> range image (numpy; offline data preparation).

Ways to turn a point cloud into an H x W image:
  * :func:`to_range_image` (:func:`unfold`) for any spinning LiDAR: rows from
    a ring field mapped by each ring's measured elevation, else from the
    nearest beam's elevation; what it drops it counts (:class:`Unfolded`);
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
from dusty_jax.errors import DataError
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

  ``cols`` is :meth:`SensorSpec.column_of`'s (column, kept): only points on
  kept firings count. With ``return_xyz`` also the (H, W, 3) points, zeros where empty.
  """
  cols, kept = cols
  keep = keep & kept
  rows, cols, xyz = rows[keep], cols[keep], xyz[keep]
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
  cols = sensor.column_of(azimuth)
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
  cols = sensor.column_of(np.arctan2(xyz[:, 1], xyz[:, 0]))
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
  cols = sensor.column_of(np.arctan2(xyz[:, 1], xyz[:, 0]))
  return _scatter_nearest(rows, cols, xyz, inside, sensor, return_xyz)


# A file whose points mostly fall outside the spec is not of this sensor.
MIN_INSIDE_SHARE = 0.5
# Nor is one whose returns on the beams and in range a spec places in far
# fewer pixels than a sweep of its sensor fills: one pixel per firing that
# its columns keep (width / native_width of them), each firing on its own
# beam. Of that norm, the real VLP-16 and PandarXT16 samples in the vlp16
# preset place 0.86-0.88, KITTI's sample in the kitti preset 0.85 (dual
# returns would place half); KITTI's in a 16-beam spec of 256 of 1800
# columns 0.18, in hdl32e at 256 columns 0.17, its beams between the spec's
# and its firings between the kept ones.
MIN_PLACED_OF_NORM = 1 / 3
# Too few returns to judge by the share they fill (a few stray points).
MIN_PLACED_EXPECTED = 100

# A ring whose median elevation lies farther than this many beam spacings
# outside the spec's top or bottom beam is not one of its beams.
RING_MARGIN_SPACINGS = 1.0


class NotThisSensor(DataError):
  """A sweep that the spec cannot be the sensor of (:func:`unfold`)."""


@dataclasses.dataclass
class Unfolded:
  """A range image and what became of each point (:func:`unfold`).

  ``depth`` (H, W) metric range, 0 where no return; ``xyz`` (H, W, 3) the
  winning points. The counts partition the points: ``no_return`` (at the
  origin or NaN: placeholders for beams without a return), ``out_of_range``
  (not inside the spec's (min_depth, max_depth)), ``off_elevation`` (farther
  than half a beam spacing outside the spec's beams, or on a ring whose
  median is), ``between_columns`` (firings between the kept ones),
  ``hidden`` (a nearer point won the pixel), ``placed``.
  ``ring_rows``: {ring id: row} where a ring field decided the rows.
  """
  depth: np.ndarray
  xyz: np.ndarray
  points: int
  no_return: int
  out_of_range: int
  off_elevation: int
  between_columns: int
  hidden: int
  placed: int
  ring_rows: dict | None

  def summary(self) -> str:
    return (f'{self.placed} of {self.points} points placed; dropped: '
            f'{self.no_return} without a return, {self.out_of_range} out of range, '
            f'{self.off_elevation} off the beams, {self.between_columns} between '
            f'kept columns, {self.hidden} behind a nearer point in their pixel')


def _spacing_margins(sensor: SensorSpec) -> tuple[float, float]:
  """Half the beam spacing above the top and below the bottom beam (radians)."""
  if sensor.height == 1:
    return np.deg2rad(1.0), np.deg2rad(1.0)
  sp = np.abs(np.diff(sensor.elevation))
  return 0.5 * sp[0], 0.5 * sp[-1]


# Passes of nearest_beam's search with the offsets of the beams it found:
# a beam's offset changes little from one beam to the next, so the search
# settles in a pass or two even where the offsets move a near point past
# several beams (an Ouster OS0's at half a metre: 2 beams of 128).
NEAREST_PASSES = 3


def nearest_beam(sin_el: np.ndarray, rng: np.ndarray, sensor: SensorSpec):
  """(row, inside) of each point: the beam whose elevation model
  ``sin(elevation) + b / range`` is nearest to the point's sin(elevation);
  ``inside``: within half a beam spacing of the outermost beams."""
  s = np.sin(sensor.elevation)[::-1]  # increasing
  b = sensor.vertical_offset[::-1]
  mid = 0.5 * (s[1:] + s[:-1])
  j = np.searchsorted(mid, sin_el)  # nearest ignoring the offsets
  if sensor.vertical_offset_m:  # then with them (near points move by
    for _ in range(NEAREST_PASSES):  # several beams), and the neighbours
      j = np.searchsorted(mid, sin_el - b[j] / rng)
    best = j
    cost = np.abs(sin_el - s[j] - b[j] / rng)
    for d in (-1, 1):
      k = np.clip(j + d, 0, len(s) - 1)
      c = np.abs(sin_el - s[k] - b[k] / rng)
      best = np.where(c < cost, k, best)
      cost = np.minimum(c, cost)
    j = best
  row = sensor.height - 1 - j
  top, bottom = _spacing_margins(sensor)
  corrected = sin_el - b[j] / rng
  inside = ((corrected <= np.sin(sensor.elevation[0] + top)) &
            (corrected >= np.sin(sensor.elevation[-1] - bottom)))
  return row, inside


def rows_from_ring_field(ring: np.ndarray, elevation: np.ndarray, in_range: np.ndarray,
                         sensor: SensorSpec, source: str):
  """({ring id: row}, row per point, whether its ring has an in-range
  return per point) from a ring field: rings ordered by the
  median elevation of their in-range returns, never by their ids, and
  matched to rows monotonically (:func:`_assign_rows`), so a ring with no
  return leaves its row empty. Only in-range returns decide: a driver's
  placeholders for beams without a return (nuScenes writes them a few
  centimetres out, and its upper rings see mostly sky) would otherwise set
  the median of a ring. Row -1: a ring off the beams, or one with no
  in-range return (its points are all out of range, placed nowhere)."""
  if ring.min() >= 0 and ring.max() < 2 ** 16:  # a counting sort: linear time
    present = np.bincount(ring) > 0
    ids = np.flatnonzero(present)
    index = np.cumsum(present) - 1
    inverse = index[ring].astype(np.uint16)
  else:
    ids, inverse = np.unique(ring, return_inverse=True)
  kept = inverse[in_range]
  order = np.argsort(kept, kind='stable')
  bounds = np.searchsorted(kept[order], np.arange(len(ids) + 1))
  elevation = elevation[in_range]
  returned = np.diff(bounds) > 0
  if returned.sum() > sensor.height:
    raise DataError(f'{source}: {int(returned.sum())} distinct ring ids, but sensor '
                    f'{sensor.name!r} has {sensor.height} beams (counting the rings with a '
                    'return in its range); is this the right sensor spec?')
  med = np.full(len(ids), np.nan)
  for i in np.flatnonzero(returned):
    med[i] = np.median(elevation[order[bounds[i]:bounds[i + 1]]])
  top, bottom = _spacing_margins(sensor)
  on = returned & (
      (med <= sensor.elevation[0] + 2 * RING_MARGIN_SPACINGS * top) &
      (med >= sensor.elevation[-1] - 2 * RING_MARGIN_SPACINGS * bottom))
  row_of = np.full(len(ids), -1, np.int64)
  idx = np.flatnonzero(on)
  if len(idx):
    by_el = idx[np.argsort(-med[idx], kind='stable')]
    row_of[by_el] = _assign_rows(med[by_el], sensor)
  return ({int(i): int(r) for i, r in zip(ids, row_of)}, row_of[inverse],
          returned[inverse])


def unfold(points, sensor: SensorSpec, ring=None, source: str = 'points') -> Unfolded:
  """Unfolds one sweep of any spinning LiDAR into an (H, W) range image.

  Args:
    points: an (N, >=3) array of x, y, z, or a dict of fields with 'x', 'y',
      'z' (data.read_points' output; its ring field is not used unless
      given as ``ring``).
    sensor: the spec that decides rows, columns and range.
    ring: optional (N,) beam ids in the driver's own order (any order: top
      first, bottom first or interleaved): rows come from the median
      elevation of each ring's in-range returns (never its placeholders
      near the origin). Without it each point goes to the nearest beam's elevation
      (with the spec's vertical offsets where it has them).
    source: names the input (a path) in errors.

  Each image column keeps the returns in its first native column's worth
  of azimuth (SensorSpec.column_of: decimation, as the authors subsample
  KITTI, so a dropped firing stays a drop). Where a driver rounds azimuths
  (a VLP-16 writes steps of 0.19 and 0.20 degrees) a window can miss its
  firing: on the real VLP-16 and PandarXT16 samples 5% and 1.8% of pixels
  are empty where a firing elsewhere in their column returned
  (benchmarks/sensors.py). Where two points fall in one pixel the nearer is
  kept (dual returns). Points at the origin or NaN (placeholders of
  beams without a return), outside the spec's range, or off its beams are
  dropped and counted. A sweep whose returns mostly fall outside the spec, or
  whose returns on its beams fill far fewer pixels than a sweep of its sensor
  (below MIN_PLACED_OF_NORM of width / native_width of them: another
  sensor's beams and firings between the spec's), is refused (NotThisSensor,
  a DataError naming ``source`` and what it found against the spec).
  """
  if isinstance(points, dict):
    try:
      xyz = np.stack([np.asarray(points[k], np.float64) for k in 'xyz'], 1)
    except KeyError as e:
      raise DataError(f'{source}: no {e} field among {sorted(points)}') from None
  else:
    xyz = np.asarray(points, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] < 3:
      raise DataError(f'{source}: expected an (N, >=3) array of points, got '
                      f'shape {xyz.shape}')
    xyz = xyz[:, :3]
  n = len(xyz)
  if ring is not None:
    ring = np.asarray(ring)
    if ring.shape != (n,):
      raise DataError(f'{source}: {ring.size} ring ids for {n} points')
  rng = np.sqrt(np.einsum('ij,ij->i', xyz, xyz))
  returned = np.isfinite(rng) & (rng > 0)
  if not returned.any():
    raise DataError(f'{source}: none of its {n} points is a return (all at '
                    'the origin or NaN)')
  xyz, rng = xyz[returned], rng[returned]
  sin_el = xyz[:, 2] / rng
  in_range = (rng > sensor.min_depth) & (rng < sensor.max_depth)
  ring_rows = None
  if ring is not None:
    ring = ring[returned]
    if not np.isfinite(ring).all() or (ring != np.round(ring)).any():
      raise DataError(f'{source}: the ring field holds values that are not '
                      'integers')
    ring_rows, row, ring_in_range = rows_from_ring_field(
        ring.astype(np.int64), np.arcsin(np.clip(sin_el, -1, 1)), in_range, sensor, source)
    # A ring without an in-range return is counted out of range, not off the beams.
    inside = (row >= 0) | ~ring_in_range
    row = np.maximum(row, 0)
  else:
    row, inside = nearest_beam(sin_el, rng, sensor)
  outside = int((~inside).sum())
  if 1 - np.mean(inside & in_range) > MIN_INSIDE_SHARE:
    el = np.rad2deg(np.arcsin(np.clip(sin_el, -1, 1)))
    lo, hi = np.percentile(el, [1, 99])
    raise NotThisSensor(
        f'{source}: {np.mean(~inside):.0%} of its returns lie off the beams and '
        f'{np.mean(~in_range):.0%} outside the range of sensor {sensor.name!r}: '
        f'its elevations span {lo:.1f} to {hi:.1f} degrees (1st-99th '
        f'percentile), the spec\'s {sensor.elevation_deg[-1]:.1f} to '
        f'{sensor.elevation_deg[0]:.1f} degrees, its range '
        f'({sensor.min_depth}, {sensor.max_depth}) m; is this the right sensor?')
  azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
  if sensor.azimuth_offset_deg:
    azimuth = azimuth - sensor.azimuth_offset[row]
  col, kept = sensor.column_of(azimuth)
  use = inside & in_range & kept
  # The nearest return of each pixel: a running minimum per pixel (linear
  # time; a sort by range costs 100x more for 100k points).
  h, w = sensor.shape
  pixel = row[use] * w + col[use]
  best = np.full(h * w, np.inf)
  np.minimum.at(best, pixel, rng[use])
  wins = rng[use] == best[pixel]
  image = np.zeros((h * w, 3), np.float32)
  image[pixel[wins]] = xyz[use][wins]
  seen = np.isfinite(best)
  depth = np.where(seen, best, 0.0).astype(np.float32).reshape(h, w)
  placed = int(seen.sum())
  eligible = int((inside & in_range).sum())
  norm = sensor.width / sensor.native_width
  if (eligible * norm >= MIN_PLACED_EXPECTED and
      placed < MIN_PLACED_OF_NORM * norm * eligible):
    raise NotThisSensor(
        f'{source}: not a sweep of sensor {sensor.name!r}: {placed:,} of its {eligible:,} '
        f'returns on the beams and in range fill a pixel ({placed / eligible:.1%}), where '
        f'a sweep of the spec fills one per kept firing ({norm:.1%}: width '
        f'{sensor.width} of native_width {sensor.native_width}); another sensor\'s '
        'sweep (move it out), or a spec whose beams or firings are not this data\'s')
  image = image.reshape(h, w, 3)
  return Unfolded(
      depth=depth, xyz=image, points=n, no_return=int(n - returned.sum()),
      out_of_range=int((inside & ~in_range).sum()), off_elevation=outside,
      between_columns=int((inside & in_range & ~kept).sum()),
      hidden=int(use.sum()) - placed, placed=placed, ring_rows=ring_rows)


def to_range_image(points, sensor: SensorSpec, ring=None,
                   source: str = 'points') -> np.ndarray:
  """(H, W) float32 metric depth of one sweep, 0 where no return, row 0 the
  top beam and column 0 at the rear (:func:`unfold`, which also says what
  it dropped)."""
  return unfold(points, sensor, ring=ring, source=source).depth


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
