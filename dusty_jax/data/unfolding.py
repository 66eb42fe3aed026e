"""Point cloud -> range image (numpy; offline data preparation).

:func:`unfold` turns one sweep of any spinning LiDAR into an H x W range
image and counts what it dropped (:class:`Unfolded`). Its rows come from

  * a ring field (the driver's beam ids, in any numbering): each ring's
    measured elevation, matched to the spec's beams (:func:`rows_from_ring_field`);
  * the sensor's firing order, for files that store points ring after ring
    (KITTI): a ring ends where the azimuth falls back, as the authors unfold
    KITTI (:func:`rows_from_firing_order`);
  * else each point's nearest beam (:func:`nearest_beam`).

Its columns come from the azimuth (SensorSpec.column_of), and the nearest
return wins each pixel (:func:`_scatter_nearest`, the one scatter).

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

# Within a ring the azimuth only grows (up to jitter far below this).
RING_BREAK_AZIMUTH = np.deg2rad(10.0)
# A file in firing order whose rings are fewer than the spec's beams is also
# split where the elevation jumps by this share of the beam spacing.
RING_BREAK_SPACINGS = 0.6

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

# Passes of nearest_beam's search with the offsets of the beams it found:
# a beam's offset changes little from one beam to the next, so the search
# settles in a pass or two even where the offsets move a near point past
# several beams (an Ouster OS0's at half a metre: 2 beams of 128).
NEAREST_PASSES = 3


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
  ``hidden`` (a nearer point won the pixel), ``placed``; in firing order
  (:func:`unfold`) the points out of range compete for their pixel all the
  same. ``ring_rows``: {ring id: row} where a ring field or the firing
  order decided the rows (row -1: a ring off the beams).
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


def check_points(points, source: str = 'points', finite: bool = False) -> np.ndarray:
  """(N, 3) float64 x, y, z of an (N, >=3) array, or of a dict of fields with
  'x', 'y', 'z' (data.read_points' output). One DataError naming ``source``
  for another shape, no points, or (with ``finite``) NaN or inf coordinates."""
  if isinstance(points, dict):
    try:
      xyz = np.stack([np.asarray(points[k], np.float64) for k in 'xyz'], 1)
    except KeyError as e:
      raise DataError(f'{source}: no {e} field among {sorted(points)}') from None
  else:
    xyz = np.asarray(points)
    if xyz.ndim != 2 or xyz.shape[1] < 3:
      raise DataError(f'{source}: expected an (N, >=3) array of points, got '
                      f'shape {xyz.shape}')
    xyz = xyz[:, :3].astype(np.float64)
  if not len(xyz):
    raise DataError(f'{source}: the scan has no points')
  if finite:
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
      raise DataError(f'{source}: {int(bad.sum())} of {len(xyz)} points '
                      'have NaN or inf coordinates')
  return xyz


def _elevation(xyz: np.ndarray) -> np.ndarray:
  return np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))


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


def rows_from_firing_order(xyz: np.ndarray, sensor: SensorSpec, source: str):
  """({ring: row}, row per point) of a sweep stored in the sensor's firing
  order: ring after ring, top beam first, each ring sweeping
  counter-clockwise from straight ahead (KITTI's velodyne files).

  A ring ends where the azimuth falls back (:func:`_split_rings`) and ring i
  is row i, as the authors unfold KITTI. Where that finds fewer rings than
  the spec has beams, rings are also split where the elevation jumps, and
  matched to rows by their median elevation (:func:`_assign_rows`), so an
  empty ring leaves an empty row instead of shifting every row above it; a
  warning names ``source``. More rings than beams: a DataError.
  """
  azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
  starts = _split_rings(azimuth)
  rows_of_ring = np.arange(sensor.height)
  if len(starts) != sensor.height:
    elevation = _elevation(xyz)
    if len(starts) < sensor.height:  # rings missing or merged
      spacing = np.min(np.abs(np.diff(sensor.elevation)))
      starts = _split_rings(azimuth, elevation, RING_BREAK_SPACINGS * spacing)
    if len(starts) > sensor.height:
      raise DataError(
          f'{source}: found {len(starts)} rings but sensor {sensor.name!r} has '
          f'{sensor.height}; is this the right sensor, and is the file in '
          'sensor order?')
    ends = np.append(starts[1:], len(xyz))
    rows_of_ring = _assign_rows(
        np.array([np.median(elevation[a:b]) for a, b in zip(starts, ends)]), sensor)
    empty = sorted(set(range(sensor.height)) - set(rows_of_ring.tolist()))
    warnings.warn(f'{source}: found {len(starts)} rings, sensor {sensor.name!r} has '
                  f'{sensor.height}; rings matched to rows by elevation, rows {empty} '
                  'left empty', stacklevel=4)  # unfold's caller
  row = np.repeat(rows_of_ring, np.diff(np.append(starts, len(xyz))))
  return dict(enumerate(rows_of_ring.tolist())), row


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


def _spacing_margins(sensor: SensorSpec) -> tuple[float, float]:
  """Half the beam spacing above the top and below the bottom beam (radians)."""
  if sensor.height == 1:
    return np.deg2rad(1.0), np.deg2rad(1.0)
  sp = np.abs(np.diff(sensor.elevation))
  return 0.5 * sp[0], 0.5 * sp[-1]


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


def _rows(xyz, rng, in_range, ring, firing_order, sensor, source):
  """(row, inside, ring_rows) of every point by the rule :func:`unfold`
  names; points without a return (range 0) are inside, on row 0."""
  n = len(xyz)
  if firing_order:
    ring_rows, row = rows_from_firing_order(xyz, sensor, source)
    return row, np.ones(n, bool), ring_rows
  returned = rng > 0
  row, inside, ring_rows = np.zeros(n, np.int64), np.ones(n, bool), None
  r = rng[returned]
  sin_el = xyz[returned, 2] / r
  if ring is not None:
    ring = ring[returned]
    if not np.isfinite(ring).all() or (ring != np.round(ring)).any():
      raise DataError(f'{source}: the ring field holds values that are not integers')
    ring_rows, on, ring_in_range = rows_from_ring_field(
        ring.astype(np.int64), np.arcsin(np.clip(sin_el, -1, 1)), in_range[returned],
        sensor, source)
    # A ring without an in-range return is counted out of range, not off the beams.
    row[returned], inside[returned] = np.maximum(on, 0), (on >= 0) | ~ring_in_range
  else:
    row[returned], inside[returned] = nearest_beam(sin_el, r, sensor)
  return row, inside, ring_rows


def _scatter_nearest(row, col, rng, xyz, use, sensor: SensorSpec):
  """The nearest of the points ``use`` marks in each pixel: (H, W) float32
  depth, 0 where none; (H, W, 3) its point; (H * W,) its range, inf where
  none. A running minimum per pixel: linear time (a sort by range costs
  100x more for 100k points)."""
  h, w = sensor.shape
  pixel = row[use] * w + col[use]
  best = np.full(h * w, np.inf)
  np.minimum.at(best, pixel, rng[use])
  wins = rng[use] == best[pixel]
  image = np.zeros((h * w, 3), np.float32)
  image[pixel[wins]] = xyz[use][wins]
  depth = np.where(np.isfinite(best), best, 0.0).astype(np.float32)
  return depth.reshape(h, w), image.reshape(h, w, 3), best


def _off_the_spec(xyz, inside, in_range, sensor, source) -> NotThisSensor:
  """The refusal of a sweep whose returns mostly lie off the spec's beams or range."""
  lo, hi = np.percentile(np.rad2deg(_elevation(xyz)), [1, 99])
  return NotThisSensor(
      f'{source}: {np.mean(~inside):.0%} of its returns lie off the beams and '
      f'{np.mean(~in_range):.0%} outside the range of sensor {sensor.name!r}: '
      f'its elevations span {lo:.1f} to {hi:.1f} degrees (1st-99th '
      f'percentile), the spec\'s {sensor.elevation_deg[-1]:.1f} to '
      f'{sensor.elevation_deg[0]:.1f} degrees, its range '
      f'({sensor.min_depth}, {sensor.max_depth}) m; is this the right sensor?')


def _too_sparse(placed: int, eligible: int, sensor: SensorSpec, source: str):
  """A NotThisSensor where the ``eligible`` returns (on the beams and in
  range) fill ``placed`` pixels, far fewer than a sweep of the spec would;
  else None."""
  norm = sensor.width / sensor.native_width
  if eligible * norm < MIN_PLACED_EXPECTED or placed >= MIN_PLACED_OF_NORM * norm * eligible:
    return None
  return NotThisSensor(
      f'{source}: not a sweep of sensor {sensor.name!r}: {placed:,} of its {eligible:,} '
      f'returns on the beams and in range fill a pixel ({placed / eligible:.1%}), where '
      f'a sweep of the spec fills one per kept firing ({norm:.1%}: width '
      f'{sensor.width} of native_width {sensor.native_width}); another sensor\'s '
      'sweep (move it out), or a spec whose beams or firings are not this data\'s')


def unfold(points, sensor: SensorSpec, ring=None, source: str = 'points', *,
           firing_order: bool = False) -> Unfolded:
  """Unfolds one sweep of any spinning LiDAR into an (H, W) range image.

  Args:
    points: an (N, >=3) array of x, y, z, or a dict of fields with 'x', 'y',
      'z' (data.read_points' output; its ring field is not used unless
      given as ``ring``).
    sensor: the spec that decides rows, columns and range.
    ring: optional (N,) beam ids in the driver's own order (any order: top
      first, bottom first or interleaved): rows come from the median
      elevation of each ring's in-range returns (:func:`rows_from_ring_field`).
    source: names the input (a path) in errors.
    firing_order: the points are stored in the sensor's firing order
      (KITTI), which gives the rows (:func:`rows_from_firing_order`), and
      are unfolded by the authors' rule: every point competes for its pixel
      whatever its range, so one outside the spec's range leaves its pixel
      invalid (the codec reads it as a drop), one at the origin empty.
      Without ``ring`` or ``firing_order``: each point on its nearest beam
      (:func:`nearest_beam`, with the spec's vertical offsets where it has them).

  Each image column keeps the returns in its first native column's worth
  of azimuth (SensorSpec.column_of: decimation, as the authors subsample
  KITTI, so a dropped firing stays a drop). Where a driver rounds azimuths
  (a VLP-16 writes steps of 0.19 and 0.20 degrees) a window can miss its
  firing: on the real VLP-16 and PandarXT16 samples 5% and 1.8% of pixels
  are empty where a firing elsewhere in their column returned
  (benchmarks/sensors.py). The nearest return wins each pixel (dual
  returns). Points at the origin or NaN (placeholders of beams without a
  return), outside the spec's range, or off its beams are dropped and
  counted. A sweep whose returns mostly fall outside the spec, or whose
  returns on its beams fill far fewer pixels than a sweep of its sensor
  (below MIN_PLACED_OF_NORM of width / native_width of them: another
  sensor's beams and firings between the spec's), is refused (NotThisSensor,
  a DataError naming ``source`` and what it found against the spec).
  """
  xyz = check_points(points, source, finite=firing_order)
  n = len(xyz)
  if ring is not None:
    if firing_order:
      raise ValueError('unfold: rows from a ring field or from the firing order, not both')
    ring = np.asarray(ring)
    if ring.shape != (n,):
      raise DataError(f'{source}: {ring.size} ring ids for {n} points')
  finite = np.isfinite(xyz).all(axis=1)
  if not finite.all():  # NaN or inf: no return, at the origin from here on
    xyz = np.where(finite[:, None], xyz, 0.0)
  rng = np.sqrt(np.einsum('ij,ij->i', xyz, xyz))
  returned = rng > 0
  if not (returned.any() or firing_order):  # (KITTI's rule: an empty image, as the authors')
    raise DataError(f'{source}: none of its {n} points is a return (all at the origin or NaN)')
  in_range = (rng > sensor.min_depth) & (rng < sensor.max_depth)
  row, inside, ring_rows = _rows(xyz, rng, in_range, ring, firing_order, sensor, source)
  eligible = inside & in_range
  if returned.any() and 1 - np.mean(eligible[returned]) > MIN_INSIDE_SHARE:
    raise _off_the_spec(xyz[returned], inside[returned], in_range[returned], sensor, source)
  azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
  if sensor.azimuth_offset_deg:
    azimuth = azimuth - sensor.azimuth_offset[row]
  col, kept = sensor.column_of(azimuth)
  depth, image, best = _scatter_nearest(row, col, rng, xyz,
                                        kept if firing_order else eligible & kept, sensor)
  placed = int(((best > sensor.min_depth) & (best < sensor.max_depth)).sum())
  refusal = _too_sparse(placed, int(eligible.sum()), sensor, source)
  if refusal:
    raise refusal
  return Unfolded(
      depth=depth, xyz=image, points=n, no_return=int(n - returned.sum()),
      out_of_range=int((returned & inside & ~in_range).sum()),
      off_elevation=int((returned & ~inside).sum()),
      between_columns=int((eligible & ~kept).sum()),
      hidden=int((eligible & kept).sum()) - placed, placed=placed, ring_rows=ring_rows)


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
