"""A sensor spec estimated from recorded sweeps (``prepare --sensor auto``).

Each beam's elevation model ``sin(elevation) = a + b / range`` (the spec's
``elevation_deg`` = asin(a) and ``vertical_offset_m`` = b) is fitted to its
returns beyond FIT_MIN_RANGE (nearer ones are drivers' placeholders for no
return, a few centimetres out, or returns where a beam-origin offset bends
the model most) by least squares that drop outliers (beyond TRIM_SIGMAS
robust deviations) and refit. Where a beam's ranges leave its offset free
(a beam that sees only flat ground, all at one range) its offset follows
the sensor's geometry, fitted to the beams whose ranges pin theirs: beam
origins displaced by ``v`` vertically and ``rho`` towards each beam give
``b = v cos^2(el) - rho sin(el) cos(el)`` (rho = Ouster's
lidar_origin_to_beam_origin_mm).

The points of a beam come from the sweeps' ring field where they have one;
else from the structure of the elevations: the points' sin(elevation),
corrected by the geometry above (the ``v`` and ``rho`` that make the
elevations' histogram sharpest), fall into one cluster per beam (a spike
of a few points, alone, is a beam that sees mostly sky), and the fitted
lines then reassign every point to its nearest beam, pass after pass: a
beam whose points spread far from its line splits in two, neighbours one
line fits become one, a line whose points another fits goes (per-laser
offsets that no common geometry corrects, as Velodyne's, make clusters
that mix and split beams). The columns come from the azimuth spacing of
consecutive returns of one beam. What the points cannot say (the sensor's
mount height, its exact range limits) is a default or a bound of what was
seen, printed for review.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from dusty_jax.data import points as points_lib
from dusty_jax.errors import DataError
from dusty_jax.sensor import SensorSpec

# Returns nearer than this (metres) are not fitted: placeholders of beams
# without a return (nuScenes writes them a few centimetres out, an Ouster
# driver at its beam origins, 15-27 mm out), and the range where a beam
# origin's offset bends the elevation model by more than 0.03 degrees
# (Ouster's OS0, 27.7 mm: second order in offset / range).
FIT_MIN_RANGE = 0.5
# Points nearer than this (metres) do not vote for a beam's cluster: there a
# beam-origin offset moves the elevation most. Clusters are found twice:
# from all the points fitted, and from those beyond it; the better fit is kept.
CLUSTER_MIN_RANGE = 3.0
CLUSTER_BIN_DEG = 0.01     # histogram bins of the elevation structure
# The beam-origin geometry tried for the sharpest elevations: a vertical
# offset v (common to all beams near the horizon) and a radial one rho, on a
# coarse grid of both (every COARSE_STRIDE-th), then each on its fine grid
# within a coarse step; from at most GEOMETRY_POINTS points (an even stride
# through them).
OFFSET_GRID_M = np.linspace(-0.1, 0.1, 201)
RADIAL_GRID_M = np.linspace(-0.05, 0.05, 201)
COARSE_STRIDE = 10
GEOMETRY_POINTS = 100_000
OFFSET_MATTERS_M = 0.002   # fitted offsets all below this are left out
# A beam that sees mostly sky returns too few points to fill its bins as
# the others do; SPIKE_RETURNS of them within SPIKE_BINS bins, alone within
# SPIKE_CLEAR_BINS bins (0.1 degrees) each side, still are a beam.
SPIKE_RETURNS = 3
SPIKE_BINS = 3
SPIKE_CLEAR_BINS = 10
# The robust fit drops points farther from the line than this many robust
# standard deviations (1.4826 median absolute deviations), or than
# RESIDUAL_FLOOR where the points lie on the line (a driver's exact angles).
TRIM_SIGMAS = 4.0
RESIDUAL_FLOOR = np.sin(np.deg2rad(0.002))
# A beam's offset is fitted where its ranges pin its elevation to this
# (standard error of a, in sin(elevation)); else it follows the geometry.
PINNED = np.sin(np.deg2rad(0.01))
MIN_FIT_POINTS = 8  # fewer returns: the beam's densest group, its offset the geometry's
# Two fitted beams closer than this (degrees) at every range are one beam
# that the clusters split.
SAME_BEAM_DEG = 0.5 * CLUSTER_BIN_DEG
ONE_LINE_FACTOR = 2.0  # (_one_line)
SPLIT_FACTOR = 5.0  # (_split_wide)
# A line whose points lie this close (degrees) to another's is not a beam of
# its own: a third of the finest beam spacing of spinning LiDARs (0.1
# degrees: RoboSense's Ruby, Velodyne's VLS-128 0.11).
REDUNDANT_DEG = 0.03
REASSIGN_PASSES = 10  # most passes of fits and reassignment (_one_line_per_beam)
WIDTHS = (2048, 1024, 512, 256)  # image widths an estimate proposes
# More clusters of elevations than any spinning LiDAR has beams: the points
# have no beam structure (noise, or not a LiDAR's sweep).
MAX_BEAMS_FOUND = 1024
# Sweeps whose beam counts differ by more than this factor are of different
# sensors (a real sweep's count varies by a few: beams without a return,
# beams that touch in its elevations).
SAME_SENSOR_RATIO = 1.5
# A beam returns at most twice per firing (dual returns); one with more per
# sweep holds several beams its elevations cannot tell apart.
MAX_RETURNS_PER_FIRING = 2.5
NEAREST_CHUNK = 2 ** 22  # points x beams compared at a time (memory bound)
# Far fewer firings per revolution than any spinning LiDAR makes (Ouster's
# fewest columns are 512, a Velodyne at 20 Hz fires about 900 times): the
# returns of each "beam" found are not one beam's sweep (sparse noise, or a
# sweep thinned out).
MIN_FIRINGS = 64
# Per-laser vertical offsets as large as a Velodyne HDL-64E's (0.15-0.2 m,
# a centimetre apart) make neighbouring beams' lines cross a few metres
# out, where the returns cannot say which beam is theirs (and the model,
# first order in offset / range, bends): where the beams found from the
# elevations have offsets b this large, they are found again from the
# returns beyond NEAR_OFFSETS x max |b| alone (3 m at 0.2 m; on simulated
# HDL-64E sweeps, 2 m still mixed beams on 2 of 8), if MIN_FAR_SHARE of
# the returns lie there.
NEAR_OFFSETS = 15.0
MIN_FAR_SHARE = 0.5


@dataclasses.dataclass
class Estimate:
  """The estimated spec and how well the points fit it."""
  spec: SensorSpec
  points: int
  beams_measured: int
  beams_inferred: list  # rows whose elevation was inferred (no return)
  rms_deg: np.ndarray  # per-beam RMS of the fit, degrees (NaN if inferred)
  agreement: float  # share of points whose nearest fitted beam is their own
  firings: int  # measured firings per revolution
  near: int = 0  # returns nearer than fit_from, not fitted
  rings_left_out: list = dataclasses.field(default_factory=list)  # ring ids
  offsets_from_geometry: int = 0  # beams whose offset follows the geometry
  beyond: int = 0  # returns beyond the outermost beams found, not fitted
  fit_from: float = FIT_MIN_RANGE  # metres (NEAR_OFFSETS)

  def summary(self) -> str:
    s = self.spec
    lines = [
        f'estimated sensor {s.name!r}: {s.height} beams from '
        f'{s.elevation_deg[0]:.3f} to {s.elevation_deg[-1]:.3f} degrees, '
        f'{self.firings} firings per revolution (image width {s.width}), from '
        f'{self.points} points',
        f'  fit: median per-beam RMS {np.nanmedian(self.rms_deg):.4f} degrees, '
        f'worst {np.nanmax(self.rms_deg):.4f}; {100 * self.agreement:.2f}% of '
        'points lie nearest to their own beam',
        '  vertical offsets: ' + (
            f'{min(s.vertical_offset_m):+.4f} to {max(s.vertical_offset_m):+.4f} m'
            if s.vertical_offset_m else 'none needed') + (
            f' ({self.offsets_from_geometry} beams\' from the beams\' geometry: their '
            'ranges leave it free)' if s.vertical_offset_m and self.offsets_from_geometry
            else ''),
    ]
    if self.near:
      lines.append(f'  {self.near} returns nearer than {self.fit_from:.2f} m not fitted '
                   '(placeholders of beams without a return, or too near to tell)')
    if self.beyond:
      lines.append(f'  {self.beyond} returns beyond the outermost beams found not fitted '
                   '(beams with too few returns to find, as those that see mostly sky: '
                   'a ring field would place them)')
    if self.beams_inferred:
      lines.append(f'  rows {self.beams_inferred} had no return: their '
                   'elevations are interpolated from their ring ids, not measured')
    if self.rings_left_out:
      lines.append(f'  rings {self.rings_left_out} left out: no return beyond '
                   f'{FIT_MIN_RANGE} m, and their ids are not in elevation order to '
                   'interpolate them')
    lines.append(f'  not measured, review: mount_height {s.mount_height} m, range '
                 f'({s.min_depth}, {s.max_depth}) m')
    return '\n'.join(lines)


def _geometry(a, v, rho):
  """``b`` of beams at sin(elevation) ``a`` whose origins sit ``v`` above
  and ``rho`` out from the sensor's origin (module docstring)."""
  c = np.sqrt(np.clip(1 - a * a, 0, 1))
  return v * c * c - rho * a * c


def _robust_line(y, x):
  """(a, b, standard error of a) of ``y = a + b x`` by least
  squares that drops points beyond TRIM_SIGMAS robust deviations; b = 0
  where x barely varies."""
  use = np.ones(len(y), bool)
  for _ in range(4):
    xs, ys = x[use], y[use]
    xm = xs.mean()
    sxx = np.sum((xs - xm) ** 2)
    if sxx > 1e-12 * len(xs):
      b = np.sum((xs - xm) * (ys - ys.mean())) / sxx
      a = ys.mean() - b * xm
    else:
      a, b = np.median(ys), 0.0
    res = y - a - b * x
    scale = 1.4826 * np.median(np.abs(res[use] - np.median(res[use])))
    keep = np.abs(res) <= max(TRIM_SIGMAS * scale, RESIDUAL_FLOOR)
    if keep.sum() < MIN_FIT_POINTS or np.array_equal(keep, use):
      break
    use = keep
  n = use.sum()
  s = np.sqrt(np.sum(res[use] ** 2) / max(n - 2, 1))
  se = s * np.sqrt(1 / n + xm ** 2 / sxx) if sxx > 1e-12 * n else np.inf
  return a, b, se


def _densest(y):
  """The mean of the largest group of ``y`` within SPIKE_BINS bins of one
  of them: a beam of a few returns among strays of its neighbours (those
  too sparse to find), where their median would lie between them."""
  close = np.abs(y[:, None] - y[None, :]) <= SPIKE_BINS * np.sin(np.deg2rad(CLUSTER_BIN_DEG))
  return float(np.mean(y[close[np.argmax(close.sum(1))]]))


def _fit_lines(sin_el, inv_r, beam, n):
  """(a, b, rms of sin, offsets from the geometry) per beam id 0..n-1:
  robust lines where a beam's ranges pin its elevation (PINNED), else the
  beam's offset from the geometry fitted to those (:func:`_geometry`) and
  its median (of fewer than MIN_FIT_POINTS, its densest group); a NaN where
  a beam has no point."""
  a, b, rms = np.full(n, np.nan), np.zeros(n), np.full(n, np.nan)
  pinned, weight = np.zeros(n, bool), np.zeros(n)
  order = np.argsort(beam, kind='stable')
  bounds = np.searchsorted(beam[order], np.arange(n + 1))
  groups = [order[bounds[j]:bounds[j + 1]] for j in range(n)]
  for j, idx in enumerate(groups):
    if len(idx) >= MIN_FIT_POINTS:
      a[j], b[j], se = _robust_line(sin_el[idx], inv_r[idx])
      pinned[j] = se <= PINNED
      weight[j] = 1 / max(se, 1e-9) ** 2
  # The geometry of the pinned beams (weighted by their precision).
  v = rho = 0.0
  if pinned.sum() >= 2:
    aj = a[pinned]
    c = np.sqrt(np.clip(1 - aj * aj, 0, 1))
    design = np.stack([c * c, -aj * c], 1) * np.sqrt(weight[pinned])[:, None]
    (v, rho), *_ = np.linalg.lstsq(design, b[pinned] * np.sqrt(weight[pinned]), rcond=None)
  free = 0
  for j, idx in enumerate(groups):
    if not len(idx) or pinned[j]:
      continue
    y, x = sin_el[idx], inv_r[idx]
    centre = np.median if len(idx) >= MIN_FIT_POINTS else _densest
    a[j] = centre(y)
    for _ in range(3):  # b depends on the elevation it offsets
      b[j] = _geometry(a[j], v, rho)
      a[j] = centre(y - b[j] * x)
    free += 1
  for j, idx in enumerate(groups):
    if len(idx):
      res = sin_el[idx] - a[j] - b[j] * inv_r[idx]
      rms[j] = np.sqrt(np.mean(res ** 2))
  return a, b, rms, free


def _nearest(sin_el, inv_r, a, b, beams):
  """Of ``beams`` (ids into a, b), the one whose line ``a + b / range`` is
  nearest to each point's sin(elevation); memory bounded by NEAREST_CHUNK."""
  out = np.empty(len(sin_el), np.int64)
  step = max(1, NEAREST_CHUNK // max(len(beams), 1))
  for i in range(0, len(sin_el), step):
    y, x = sin_el[i:i + step, None], inv_r[i:i + step, None]
    out[i:i + step] = beams[np.argmin(np.abs(y - a[beams] - b[beams] * x), axis=1)]
  return out


def _runs(mask):
  """(first, last) index of each run of True in ``mask``."""
  return (np.flatnonzero(mask & ~np.r_[False, mask[:-1]]),
          np.flatnonzero(mask & ~np.r_[mask[1:], False]))


def _spikes(hist):
  """Bins of a beam with few returns (one that sees mostly sky): at least
  SPIKE_RETURNS points within SPIKE_BINS bins, and no other point within
  SPIKE_CLEAR_BINS bins of them."""
  starts, ends = _runs(hist > 0)
  total = np.add.reduceat(hist, starts) if len(starts) else np.zeros(0, hist.dtype)
  gap_before = np.r_[np.inf, starts[1:] - ends[:-1] - 1]
  gap_after = np.r_[starts[1:] - ends[:-1] - 1, np.inf]
  spike = ((total >= SPIKE_RETURNS) & (ends - starts < SPIKE_BINS) &
           (gap_before >= SPIKE_CLEAR_BINS) & (gap_after >= SPIKE_CLEAR_BINS))
  out = np.zeros(len(hist), bool)
  for s, e in zip(starts[spike], ends[spike]):
    out[s:e + 1] = True
  return out


def _clusters(sin_el, inv_r, mode, source='the sweeps'):
  """Beam ids (top first) of points by the structure of their elevations,
  their count, and which points lie within half a beam spacing of the
  outermost beams found (those beyond, returns of beams too sparse to find,
  would pull the outermost lines); DataError naming ``source`` where the
  points have no structure (MAX_BEAMS_FOUND)."""
  far = np.ones_like(inv_r, bool) if mode == 'all' else inv_r <= 1.0 / CLUSTER_MIN_RANGE
  if far.sum() < 100:  # (a sweep of a room: every point near)
    far = np.ones_like(inv_r, bool)
  y, x = sin_el[far], inv_r[far]
  lo = y.min()
  width = np.sin(np.deg2rad(CLUSTER_BIN_DEG))
  bins = max(int((y.max() - lo) / width) + 1, 1)
  stride = max(1, len(y) // GEOMETRY_POINTS)
  ys = (y[::stride] - lo) / width
  # _geometry(y, v, rho) * x = v * vx - rho * rx, in bins.
  vx, rx = _geometry(y[::stride], 1, 0) * x[::stride] / width, \
      -_geometry(y[::stride], 0, 1) * x[::stride] / width

  def sharpness(v, rho):  # (points moved beyond the elevations seen: not counted)
    k = np.floor(ys - v * vx + rho * rx).astype(np.int64)
    h = np.bincount(k[(k >= 0) & (k < bins)], minlength=bins)
    return np.sum(h.astype(np.float64) ** 2)

  # The sharpest geometry: both offsets on a coarse grid, then rho (beams'
  # origins out from the axis), v (common near the horizon) and rho again
  # on their fine grids.
  v, rho = max(((v, rho) for v in OFFSET_GRID_M[::COARSE_STRIDE]
                for rho in RADIAL_GRID_M[::COARSE_STRIDE]), key=lambda t: sharpness(*t))

  def around(grid, t):  # the fine grid within a coarse step of t
    return grid[np.abs(grid - t) <= COARSE_STRIDE * (grid[1] - grid[0]) * 1.0001]

  rho = max(around(RADIAL_GRID_M, rho), key=lambda t: sharpness(v, t))
  v = max(around(OFFSET_GRID_M, v), key=lambda t: sharpness(t, rho))
  rho = max(around(RADIAL_GRID_M, rho), key=lambda t: sharpness(v, t))
  hist, edges = np.histogram(y - _geometry(y, v, rho) * x, bins=bins)
  occupied = (hist >= max(2, 1e-4 * far.sum())) | _spikes(hist)
  # A beam is a run of occupied bins; runs split at an empty bin.
  starts, ends = _runs(occupied)
  if len(starts) > MAX_BEAMS_FOUND:
    lo_deg, hi_deg = np.rad2deg(np.arcsin(np.percentile(y, [1, 99])))
    raise DataError(
        f'{source}: no beam structure found: the elevations of its returns '
        f'({lo_deg:.1f} to {hi_deg:.1f} degrees, 1st-99th percentile) fall into '
        f'{len(starts):,} clusters, more than the {MAX_BEAMS_FOUND} beams any spinning '
        'LiDAR has; not a LiDAR sweep? Give its sensor spec instead (--sensor PATH)')
  if not len(starts):
    raise DataError(f'{source}: no beam structure found: no elevation holds '
                    f'{max(2, 1e-4 * far.sum()):.0f} returns within {CLUSTER_BIN_DEG} '
                    'degrees; give its sensor spec instead (--sensor PATH)')
  centres = np.array([np.average(0.5 * (edges[s:e + 1] + edges[s + 1:e + 2]),
                                 weights=hist[s:e + 1]) for s, e in zip(starts, ends)])
  centres = np.sort(centres)[::-1]  # top first
  b = _geometry(centres, v, rho)
  beam = _nearest(sin_el, inv_r, centres, b, np.arange(len(centres)))
  on = np.ones(len(beam), bool)
  if len(centres) > 1:
    corrected = sin_el - b[beam] * inv_r
    on = ((corrected <= centres[0] + 0.5 * (centres[0] - centres[1])) &
          (corrected >= centres[-1] - 0.5 * (centres[-2] - centres[-1])))
  return beam, len(centres), on


def _one_line(sin_el, inv_r, first, second, line1, line2) -> bool:
  """Whether one line fits the points ``first`` and ``second`` (indices)
  as well as each group's own line (``line1``, ``line2``: (a, b)) fits it:
  each group's median absolute residual from the line of both within
  ONE_LINE_FACTOR of its own (or of RESIDUAL_FLOOR); a group too small to
  fit (under MIN_FIT_POINTS) is asked to lie on the other's line. A beam the
  clusters split by range passes; two beams fail (the line of both fits one
  at most)."""
  small = [len(g) < MIN_FIT_POINTS for g in (first, second)]
  if all(small):
    return False
  if any(small):
    a, b = line2 if small[0] else line1
  else:
    a, b, _ = _robust_line(sin_el[np.r_[first, second]], inv_r[np.r_[first, second]])
  groups = (first, second)
  own = [np.median(np.abs(sin_el[g] - a_g - b_g * inv_r[g]))
         for g, (a_g, b_g) in zip(groups, (line1, line2))]
  fitted = max(o for o, s in zip(own, small) if not s)  # (a small group: the other's spread)
  return all(np.median(np.abs(sin_el[g] - a - b * inv_r[g])) <= ONE_LINE_FACTOR * max(
      fitted if s else o, RESIDUAL_FLOOR) for g, o, s in zip(groups, own, small))


def _redundant(sin_el, inv_r, beam, a, b):
  """Beams whose points another line fits as well as their own (median
  absolute residual within ONE_LINE_FACTOR of it), or within REDUNDANT_DEG:
  a line through the points where other beams' lines cross (beams with
  offsets of their own), or a piece the clusters split off a beam (its
  near points, where the model's second order moves them). Of a beam and
  the line that fits it, both redundant, the one with fewer points."""
  live = np.flatnonzero(np.isfinite(a))
  if len(live) < 3:
    return np.zeros(0, np.int64)
  own = np.abs(sin_el - a[beam] - b[beam] * inv_r)
  other = np.full(len(sin_el), np.inf)
  partner = np.zeros(len(sin_el), np.int64)
  step = max(1, NEAREST_CHUNK // len(live))
  for i in range(0, len(sin_el), step):
    d = np.abs(sin_el[i:i + step, None] - a[live] - b[live] * inv_r[i:i + step, None])
    d[beam[i:i + step, None] == live] = np.inf
    partner[i:i + step] = live[d.argmin(1)]
    other[i:i + step] = d.min(1)
  order = np.argsort(beam, kind='stable')
  bounds = np.searchsorted(beam[order], np.arange(len(a) + 1))
  count = np.diff(bounds)
  close = np.sin(np.deg2rad(REDUNDANT_DEG))
  fits = {}  # redundant beam: the line that fits it
  for j in live:
    idx = order[bounds[j]:bounds[j + 1]]
    if len(idx) and np.median(other[idx]) <= max(ONE_LINE_FACTOR * np.median(own[idx]), close):
      fits[j] = np.bincount(partner[idx]).argmax()
  return np.array([j for j, k in fits.items()
                   if k not in fits or (count[j], -j) < (count[k], -k)], np.int64)


def _split_wide(sin_el, inv_r, beam, n, a, b):
  """(beam ids, count) with each beam whose points spread from its line
  SPLIT_FACTOR times more than a typical beam's (median absolute
  residuals) split in two, above and below its line: two beams the
  clusters merged, which no reassignment to the nearest line parts."""
  res = sin_el - a[beam] - b[beam] * inv_r
  count = np.bincount(beam, minlength=n)
  spread = np.full(n, np.nan)
  order = np.argsort(beam, kind='stable')
  bounds = np.searchsorted(beam[order], np.arange(n + 1))
  for j in np.flatnonzero(count >= 2 * MIN_FIT_POINTS):
    spread[j] = np.median(np.abs(res[order[bounds[j]:bounds[j + 1]]]))
  if np.isnan(spread).all():
    return beam, n
  wide = np.flatnonzero(spread > SPLIT_FACTOR * max(np.nanmedian(spread), RESIDUAL_FLOOR))
  beam = beam.copy()
  for k, j in enumerate(wide):
    beam[(beam == j) & (res > 0)] = n + k
  return beam, n + len(wide)


def _one_line_per_beam(sin_el, inv_r, beam, n):
  """Beam ids 0..m-1 (top first) and m after passes (REASSIGN_PASSES at
  most, until nothing changes) in which the fitted lines reassign every
  point to its nearest: a beam spread wide splits (:func:`_split_wide`), a
  line another makes redundant goes (:func:`_redundant`), beams left
  without a point go, and neighbours whose elevations (or lines, over the
  ranges seen) lie within SAME_BEAM_DEG of each other, or that one line
  fits (:func:`_one_line`), become one."""
  x_lo, x_hi = inv_r.min(), inv_r.max()
  for _ in range(REASSIGN_PASSES):
    a, b, _, _ = _fit_lines(sin_el, inv_r, beam, n)
    beam, n_split = _split_wide(sin_el, inv_r, beam, n, a, b)
    if n_split > n:
      n = n_split
      a, b, _, _ = _fit_lines(sin_el, inv_r, beam, n)
    a[_redundant(sin_el, inv_r, beam, a, b)] = np.nan  # (its points go to the others)
    live = np.flatnonzero(np.isfinite(a))
    live = live[np.argsort(-a[live], kind='stable')]
    # Neighbours in elevation whose lines stay within SAME_BEAM_DEG, or
    # whose points one line fits as well as each its own.
    tol = np.sin(np.deg2rad(SAME_BEAM_DEG))
    gap = np.minimum(np.abs(np.diff(a[live])), np.maximum(
        np.abs(np.diff(a[live]) + np.diff(b[live]) * x_lo),
        np.abs(np.diff(a[live]) + np.diff(b[live]) * x_hi)))
    apart = gap > tol
    order = np.argsort(beam, kind='stable')
    bounds = np.searchsorted(beam[order], np.arange(n + 1))
    for k in np.flatnonzero(apart):
      i, j = live[k], live[k + 1]
      apart[k] = not _one_line(sin_el, inv_r, order[bounds[i]:bounds[i + 1]],
                               order[bounds[j]:bounds[j + 1]], (a[i], b[i]), (a[j], b[j]))
    merged = np.r_[0, np.cumsum(apart)]  # a new beam at each wide gap
    new_id = np.empty(n, np.int64)
    new_id[live] = merged
    before = beam
    beam = new_id[_nearest(sin_el, inv_r, a, b, live)]
    # Ids of the beams left with points, in elevation order.
    present = np.bincount(beam, minlength=int(merged[-1]) + 1) > 0
    beam = (np.cumsum(present) - 1)[beam]
    stable = present.sum() == n and np.array_equal(beam, before)
    n = int(present.sum())
    if stable:
      break
  return beam, n


def _beam_count(p, ring, source) -> int:
  """Beams in one sweep: its ring ids, else its clusters of elevations."""
  if ring is not None:
    return len(np.unique(ring))
  rng = np.linalg.norm(p, axis=1)
  keep = np.isfinite(rng) & (rng >= FIT_MIN_RANGE)
  if keep.sum() < 100:
    raise DataError(f'{source}: only {int(keep.sum())} returns beyond {FIT_MIN_RANGE} m; a '
                    'sweep has thousands')
  return _clusters(p[keep, 2] / rng[keep], 1.0 / rng[keep], 'far', source)[1]


def _check_one_sensor(xyz, rings, sources):
  """DataError naming two sweeps where their beam counts say they are of
  different sensors (SAME_SENSOR_RATIO)."""
  counts = [_beam_count(p, r, s) for p, r, s in zip(xyz, rings, sources)]
  lo, hi = int(np.argmin(counts)), int(np.argmax(counts))
  if counts[hi] > SAME_SENSOR_RATIO * counts[lo]:
    raise DataError(
        f'the sweeps to estimate from are of different sensors: {sources[hi]} shows '
        f'{counts[hi]} beams, {sources[lo]} {counts[lo]} (beam counts of all '
        f'{len(counts)}: {counts}); estimate from one sensor\'s sweeps: move the others '
        'out, or list one sensor\'s in train.txt')


def _firings(azimuth, beam, n, source) -> int:
  """Firings per revolution from the median azimuth step within a beam;
  DataError naming ``source`` where there are too few to measure, or fewer
  than MIN_FIRINGS (no beam's returns follow each other around)."""
  steps = []
  for j in range(n):
    a = np.sort(azimuth[beam == j])
    if len(a) > 2:
      d = np.diff(a)
      steps.append(d[d > 1e-4])
  steps = np.concatenate(steps) if steps else np.array([])
  if not steps.size:
    raise DataError(f'{source}: too few points per beam to measure the azimuth spacing; '
                    'give its sensor spec instead (--sensor PATH)')
  firings = int(round(2 * np.pi / np.median(steps)))
  if firings < MIN_FIRINGS:
    raise DataError(
        f'{source}: no beam structure found: the returns of one beam lie '
        f'{np.rad2deg(np.median(steps)):.1f} degrees apart in azimuth on the median '
        f'({firings} per revolution), where a spinning LiDAR fires at least {MIN_FIRINGS} '
        'times a revolution; not a LiDAR sweep, or one thinned out? Give its sensor spec '
        'instead (--sensor PATH)')
  return firings


def _named(sources) -> str:
  """The sweeps of an estimate in a few words: one or two by name, else the
  first and how many more."""
  if len(sources) <= 2:
    return ' and '.join(sources)
  return f'{sources[0]} and {len(sources) - 1} more sweeps'


def _check_beams(a, own, firings, sweeps, sources):
  """DataError for fewer than two beams, or a beam with more returns per
  sweep than its firings allow (MAX_RETURNS_PER_FIRING): beams merged."""
  per_sweep = np.bincount(own, minlength=len(a)) / sweeps
  worst = int(np.argmax(per_sweep))
  el = np.rad2deg(np.arcsin(np.clip(a, -1, 1)))
  merged = per_sweep[worst] > MAX_RETURNS_PER_FIRING * firings
  if len(a) >= 2 and not merged:
    return
  found = f'found {len(a)} beam{"s" if len(a) > 1 else ""} in {_named(sources)}'
  why = (f'the one at {el[worst]:.3f} degrees has {per_sweep[worst]:,.0f} returns per '
         f'sweep, {per_sweep[worst] / firings:.1f} per firing of the {firings} measured: '
         'several beams merged' if merged else 'a range image needs several')
  raise DataError(
      f'{found}; {why}; beams closer than {CLUSTER_BIN_DEG} degrees cannot be told apart '
      'by their elevations: give the sensor\'s spec instead (--sensor PATH)')


def estimate(sweeps, ring=None, name: str = 'estimated',
             mount_height: float = 1.73, width: int | None = None,
             sources=None) -> Estimate:
  """Estimates a sensor spec from one or more sweeps.

  Args:
    sweeps: field dicts (data.points.read_points) or (N, >=3) arrays.
    ring: per sweep, its ring ids (None where a sweep has none); by default
      each dict's ring field (points.ring_field) where it has one. Rings
      are ordered by their fitted elevation, never by their ids.
    name: the spec's name.
    mount_height: not measurable from the points; recorded as given.
    width: image columns; default the largest of WIDTHS not above the
      measured firings per revolution.
    sources: per sweep, its name (a path) for errors.

  Refused, in a DataError naming the sweeps: sweeps whose beam counts say
  they are of different sensors; points with no beam structure (more
  clusters of elevations than MAX_BEAMS_FOUND); fewer than two beams, or a
  beam with more returns per sweep than MAX_RETURNS_PER_FIRING times the
  firings (beams closer than the elevations tell apart, merged).
  """
  xyz, rings = _as_points(sweeps, ring)
  sources = list(sources) if sources is not None else [f'sweep {i}' for i in range(len(xyz))]
  if len(xyz) > 1:
    _check_one_sensor(xyz, rings, sources)
  named = _named(sources)
  returns = _returns(xyz, rings, named)
  if returns.ring is not None:
    beams, beyond = _beams_by_ring(returns), 0
    ranges = returns.r
  else:
    beams, on = _beams_by_elevation(returns, named)
    ranges = returns.r[on]  # (the spec's range: of all the returns the beams hold)
    reach = float(NEAR_OFFSETS * np.nanmax(np.abs(beams.b)))
    far = returns.r >= reach
    if not far.all() and far.mean() >= MIN_FAR_SHARE and far.sum() >= 100:
      returns = dataclasses.replace(returns.where(far), near=returns.near + int((~far).sum()),
                                    fit_from=reach)
      beams, on = _beams_by_elevation(returns, named)
    returns, beyond = returns.where(on), int((~on).sum())
  top_first = np.argsort(-beams.a, kind='stable')
  a, b, rms, ids = (x[top_first] for x in (beams.a, beams.b, beams.rms, beams.ids))
  inferred = [int(i) for i, u in enumerate(ids) if int(u) in beams.inferred_ids]
  row_of = np.empty(len(top_first), np.int64)
  row_of[top_first] = np.arange(len(top_first))
  own = row_of[beams.beam]  # each return's row of the image
  firings = _firings(returns.azimuth, own, len(a), named)
  _check_beams(a, own, firings, len(xyz), sources)
  spec = _spec(name, a, b, ranges, firings, width, mount_height, named)
  # Agreement: each point's nearest fitted beam against its own.
  nearest = _nearest(returns.sin_el, returns.inv_r, a, b, np.arange(len(a)))
  return Estimate(spec, points=len(returns.r), beams_measured=len(a) - len(inferred),
                  beams_inferred=inferred, rms_deg=np.rad2deg(rms),
                  agreement=float(np.mean(nearest == own)), firings=firings,
                  near=returns.near, rings_left_out=beams.left_out,
                  offsets_from_geometry=int(beams.free), beyond=beyond,
                  fit_from=returns.fit_from)


def _as_points(sweeps, ring):
  """(xyz, rings) per sweep: its (N, 3) float64 points and its ring ids
  (``ring``'s, else a dict's ring field; None where it has none)."""
  xyz, rings = [], []
  sweeps = list(sweeps)
  if not sweeps:
    raise DataError('estimate: no sweep given')
  for i, s in enumerate(sweeps):
    if isinstance(s, dict):
      p = np.stack([np.asarray(s[k], np.float64) for k in 'xyz'], 1)
      r = points_lib.ring_field(s) if ring is None else ring[i]
    else:
      p = np.asarray(s, np.float64)[:, :3]
      r = None if ring is None else ring[i]
    rings.append(None if r is None else np.asarray(r))
    xyz.append(p)
  return xyz, rings


@dataclasses.dataclass
class _Returns:
  """The returns fitted (those beyond FIT_MIN_RANGE) of all the sweeps."""
  r: np.ndarray  # range, metres
  sin_el: np.ndarray  # sin(elevation)
  inv_r: np.ndarray  # 1 / range
  azimuth: np.ndarray  # radians
  ring: np.ndarray | None  # ring ids, where every sweep has them
  rings_seen: np.ndarray | None  # the ring ids of all returns, near ones too
  near: int  # returns nearer than fit_from, left out
  fit_from: float = FIT_MIN_RANGE

  def where(self, keep) -> _Returns:
    """The returns ``keep`` (a mask) selects."""
    return dataclasses.replace(self, r=self.r[keep], sin_el=self.sin_el[keep],
                               inv_r=self.inv_r[keep], azimuth=self.azimuth[keep],
                               ring=None if self.ring is None else self.ring[keep])


def _returns(xyz, rings, named) -> _Returns:
  """The returns of the sweeps (points, ring ids) beyond FIT_MIN_RANGE;
  DataError naming the sweeps (``named``) where fewer than 100 are."""
  rng = [np.linalg.norm(p, axis=1) for p in xyz]
  returned = [np.isfinite(r) & (r > 0) for r in rng]
  keep = [k & (r >= FIT_MIN_RANGE) for r, k in zip(rng, returned)]
  near = int(sum(k.sum() for k in returned) - sum(k.sum() for k in keep))
  p = np.concatenate([a[k] for a, k in zip(xyz, keep)])
  r = np.concatenate([a[k] for a, k in zip(rng, keep)])
  if len(p) < 100:
    raise DataError(f'{named}: only {len(p)} returns beyond {FIT_MIN_RANGE} m to estimate '
                    f'a sensor from ({near} nearer: placeholders of beams without a '
                    'return?); a sweep has thousands')
  ring = seen = None
  if all(x is not None for x in rings):
    ring = np.concatenate([a[k] for a, k in zip(rings, keep)]).astype(np.int64)
    seen = np.unique(np.concatenate([a[k] for a, k in zip(rings, returned)]))
  return _Returns(r=r, sin_el=p[:, 2] / r, inv_r=1.0 / r,
                  azimuth=np.arctan2(p[:, 1], p[:, 0]), ring=ring, rings_seen=seen,
                  near=near)


@dataclasses.dataclass
class _Beams:
  """The beams found in the returns: per beam its line sin(elevation) = a +
  b / range, the line's RMS (of sin; NaN for a beam without a return) and
  its id (ring id, or cluster); per return, its beam (an index into
  them)."""
  beam: np.ndarray
  a: np.ndarray
  b: np.ndarray
  rms: np.ndarray
  ids: np.ndarray
  free: int  # beams whose offset follows the geometry (_fit_lines)
  inferred_ids: set = dataclasses.field(default_factory=set)  # ids without a return
  left_out: list = dataclasses.field(default_factory=list)  # ring ids not placed


def _beams_by_ring(returns: _Returns) -> _Beams:
  """One beam per ring id, a line fitted to its returns. Ring ids 0..max
  with some never seen (or seen only nearer than FIT_MIN_RANGE): a ring
  without a return still is a beam; its elevation follows its neighbours'
  in id order where elevation is monotone in the id (it is for Velodyne,
  Hesai and Ouster drivers, not nuScenes'); else it is left out."""
  uniq, beam = np.unique(returns.ring, return_inverse=True)
  a, b, rms, free = _fit_lines(returns.sin_el, returns.inv_r, beam, len(uniq))
  seen = returns.rings_seen
  full = np.arange(max(uniq.max(), seen.max()) + 1) if seen.min() >= 0 else seen
  missing = np.setdiff1d(full, uniq)
  if not (len(missing) and len(uniq) >= 2 and (
      np.all(np.diff(a) > 0) or np.all(np.diff(a) < 0))):
    return _Beams(beam, a, b, rms, uniq, free,
                  left_out=sorted(set(seen.tolist()) - set(uniq.tolist())))
  fill = np.interp(missing, uniq, a, left=np.nan, right=np.nan)
  out = np.isnan(fill)  # beyond the ends: extrapolate the end spacing
  for k in np.flatnonzero(out):
    end = 0 if missing[k] < uniq[0] else -1
    step = (a[1] - a[0]) / (uniq[1] - uniq[0]) if end == 0 else (
        (a[-1] - a[-2]) / (uniq[-1] - uniq[-2]))
    fill[k] = a[end] + step * (missing[k] - uniq[end])
  return _Beams(beam, np.concatenate([a, fill]),
                np.concatenate([b, np.interp(missing, uniq, b)]),  # (beyond the ends: the end's)
                np.concatenate([rms, np.full(len(missing), np.nan)]),
                np.concatenate([uniq, missing]), free, inferred_ids=set(missing.tolist()))


def _beams_by_elevation(returns: _Returns, named: str):
  """(beams, on) from the structure of the returns' elevations
  (:func:`_clusters`, then :func:`_one_line_per_beam`), clustered twice
  (all returns vote, or only the far ones) and the clustering whose lines
  lie nearer to every return kept; ``on``: the returns within the
  outermost beams, those the beams hold."""
  sin_el, inv_r = returns.sin_el, returns.inv_r
  best = None
  for mode in ('all', 'far'):
    beam, n, on = _clusters(sin_el, inv_r, mode, named)
    beam, n = _one_line_per_beam(sin_el[on], inv_r[on], beam[on], n)
    a, b, rms, free = _fit_lines(sin_el[on], inv_r[on], beam, n)
    # How far every point lies from its nearest line (those not fitted too).
    closest = _nearest(sin_el, inv_r, a, b, np.arange(n))
    score = np.sqrt(np.mean((sin_el - a[closest] - b[closest] * inv_r) ** 2))
    if best is None or score < best[0]:
      best = (score, _Beams(beam, a, b, rms, np.arange(n), free), on)
  return best[1:]


def _spec(name, a, b, r, firings, width, mount_height, named) -> SensorSpec:
  """The SensorSpec of beams' lines (a, b; top first), the returns' ranges
  ``r`` and the firings per revolution; ``width`` None: the largest of
  WIDTHS not above the firings."""
  if width is None:
    width = next((w for w in WIDTHS if w <= firings), max(16, firings // 16 * 16))
  offsets = b if np.max(np.abs(b)) >= OFFSET_MATTERS_M else ()
  elevation = np.rad2deg(np.arcsin(np.clip(a, -1, 1)))
  try:
    return SensorSpec(
        name, tuple(round(float(e), 5) for e in elevation), width=int(width),
        native_width=max(firings, int(width)),
        min_depth=float(max(0.05, np.floor(0.9 * r.min() * 100) / 100)),
        max_depth=float(max(120.0, np.ceil(1.05 * r.max()))),
        mount_height=float(mount_height),
        vertical_offset_m=tuple(round(float(v), 6) for v in offsets))
  except ValueError as e:  # (what the checks above should have refused)
    raise DataError(f'{named}: could not fit a sensor spec: {e}') from None
