"""A sensor spec estimated from recorded sweeps (``prepare --sensor auto``).

Each beam's elevation model ``sin(elevation) = a + b / range`` (the spec's
``elevation_deg`` = asin(a) and ``vertical_offset_m`` = b) is fitted by least
squares to its points. The points of a beam come from the sweeps' ring field
where they have one; else from the structure of the elevations: the points'
sin(elevation), corrected by one offset common to all beams (the one that
makes the elevations' histogram sharpest), fall into one cluster per beam,
and the fitted lines then reassign every point to its nearest beam. The
columns come from the azimuth spacing of consecutive returns of one beam.
What the points cannot say (the sensor's mount height, its exact range
limits) is a default or a bound of what was seen, printed for review.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from dusty_jax.data import points as points_lib
from dusty_jax.errors import DataError
from dusty_jax.sensor import SensorSpec

# Points nearer than this (metres) do not vote for a beam's cluster: there a
# beam-origin offset moves the elevation most.
CLUSTER_MIN_RANGE = 3.0
CLUSTER_BIN_DEG = 0.01     # histogram bins of the elevation structure
OFFSET_GRID_M = np.linspace(-0.1, 0.1, 201)  # the common offsets tried
OFFSET_MATTERS_M = 0.002   # fitted offsets all below this are left out
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
            if s.vertical_offset_m else 'none needed'),
    ]
    if self.beams_inferred:
      lines.append(f'  rows {self.beams_inferred} had no return: their '
                   'elevations are interpolated from their ring ids, not measured')
    lines.append(f'  not measured, review: mount_height {s.mount_height} m, range '
                 f'({s.min_depth}, {s.max_depth}) m')
    return '\n'.join(lines)


def _fit_lines(sin_el, inv_r, beam, n):
  """Least-squares (a, b, rms of sin) per beam id 0..n-1."""
  a, b, rms = np.full(n, np.nan), np.zeros(n), np.full(n, np.nan)
  order = np.argsort(beam, kind='stable')
  bounds = np.searchsorted(beam[order], np.arange(n + 1))
  for j in range(n):
    idx = order[bounds[j]:bounds[j + 1]]
    if not len(idx):
      continue
    y, x = sin_el[idx], inv_r[idx]
    if len(idx) >= 8 and np.ptp(x) > 1e-3:
      design = np.stack([np.ones_like(x), x], 1)
      (a[j], b[j]), *_ = np.linalg.lstsq(design, y, rcond=None)
    else:
      a[j] = np.median(y)
    rms[j] = np.sqrt(np.mean((y - a[j] - b[j] * x) ** 2))
  return a, b, rms


def _nearest(sin_el, inv_r, a, b, beams):
  """Of ``beams`` (ids into a, b), the one whose line ``a + b / range`` is
  nearest to each point's sin(elevation); memory bounded by NEAREST_CHUNK."""
  out = np.empty(len(sin_el), np.int64)
  step = max(1, NEAREST_CHUNK // max(len(beams), 1))
  for i in range(0, len(sin_el), step):
    y, x = sin_el[i:i + step, None], inv_r[i:i + step, None]
    out[i:i + step] = beams[np.argmin(np.abs(y - a[beams] - b[beams] * x), axis=1)]
  return out


def _clusters(sin_el, inv_r, mode, source='the sweeps'):
  """Beam ids (top first) of points by the structure of their elevations;
  DataError naming ``source`` where they have none (MAX_BEAMS_FOUND)."""
  far = np.ones_like(inv_r, bool) if mode == 'all' else inv_r < 1.0 / CLUSTER_MIN_RANGE
  if far.sum() < 100:  # (a sweep of a room: every point near)
    far = np.ones_like(inv_r, bool)
  y, x = sin_el[far], inv_r[far]
  lo, hi = y.min(), y.max()
  bins = max(int((hi - lo) / np.sin(np.deg2rad(CLUSTER_BIN_DEG))) + 1, 1)

  def sharpness(c):
    h, _ = np.histogram(y - c * x, bins=bins)
    return np.sum(h.astype(np.float64) ** 2)

  common = max(OFFSET_GRID_M, key=sharpness)
  corrected = sin_el - common * inv_r
  hist, edges = np.histogram(corrected[far], bins=bins)
  occupied = hist >= max(2, 1e-4 * far.sum())
  # A beam is a run of occupied bins; runs split at an empty bin.
  starts = np.flatnonzero(occupied & ~np.r_[False, occupied[:-1]])
  ends = np.flatnonzero(occupied & ~np.r_[occupied[1:], False])
  if len(starts) > MAX_BEAMS_FOUND:
    lo_deg, hi_deg = np.rad2deg(np.arcsin(np.percentile(y, [1, 99])))
    raise DataError(
        f'{source}: no beam structure found: the elevations of its returns '
        f'({lo_deg:.1f} to {hi_deg:.1f} degrees, 1st-99th percentile) fall into '
        f'{len(starts):,} clusters, more than the {MAX_BEAMS_FOUND} beams any spinning '
        'LiDAR has; not a LiDAR sweep? Give its sensor spec instead (--sensor PATH)')
  centres = np.array([np.average(0.5 * (edges[s:e + 1] + edges[s + 1:e + 2]),
                                 weights=hist[s:e + 1]) for s, e in zip(starts, ends)])
  centres = np.sort(centres)[::-1]  # top first
  beam = _nearest(corrected, np.zeros_like(corrected), centres, np.zeros_like(centres),
                  np.arange(len(centres)))
  return beam, len(centres), common


def _beam_count(p, ring, source) -> int:
  """Beams in one sweep: its ring ids, else its clusters of elevations."""
  if ring is not None:
    return len(np.unique(ring))
  rng = np.linalg.norm(p, axis=1)
  keep = np.isfinite(rng) & (rng > 0)
  if keep.sum() < 100:
    raise DataError(f'{source}: only {int(keep.sum())} returns; a sweep has thousands')
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


def _firings(azimuth, beam, n) -> int:
  """Firings per revolution from the median azimuth step within a beam."""
  steps = []
  for j in range(n):
    a = np.sort(azimuth[beam == j])
    if len(a) > 2:
      d = np.diff(a)
      steps.append(d[d > 1e-4])
  steps = np.concatenate(steps) if steps else np.array([])
  if not steps.size:
    raise DataError('too few points per beam to measure the azimuth spacing')
  return int(round(2 * np.pi / np.median(steps)))


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
  sources = list(sources) if sources is not None else [f'sweep {i}' for i in range(len(xyz))]
  if len(xyz) > 1:
    _check_one_sensor(xyz, rings, sources)
  use_ring = all(r is not None for r in rings)
  rng = [np.linalg.norm(p, axis=1) for p in xyz]
  keep = [np.isfinite(r) & (r > 0) for r in rng]
  p = np.concatenate([a[k] for a, k in zip(xyz, keep)])
  r = np.concatenate([a[k] for a, k in zip(rng, keep)])
  if len(p) < 100:
    raise DataError(f'estimate: only {len(p)} returns; a sweep has thousands')
  sin_el, inv_r = p[:, 2] / r, 1.0 / r
  azimuth = np.arctan2(p[:, 1], p[:, 0])
  if use_ring:
    ids = np.concatenate([a[k] for a, k in zip(rings, keep)]).astype(np.int64)
    uniq, beam = np.unique(ids, return_inverse=True)
    a, b, rms = _fit_lines(sin_el, inv_r, beam, len(uniq))
    # Ring ids 0..max with some never seen: a ring without a return still
    # is a beam; its elevation follows its neighbours' in id order where
    # elevation is monotone in the id (it is for Velodyne and Hesai drivers).
    full = np.arange(uniq.max() + 1) if uniq.min() >= 0 else uniq
    missing = np.setdiff1d(full, uniq)
    if len(missing) and len(uniq) >= 2 and (
        np.all(np.diff(a) > 0) or np.all(np.diff(a) < 0)):
      fill = np.interp(missing, uniq, a, left=np.nan, right=np.nan)
      out = np.isnan(fill)  # beyond the ends: extrapolate the end spacing
      for k in np.flatnonzero(out):
        end = 0 if missing[k] < uniq[0] else -1
        step = (a[1] - a[0]) / (uniq[1] - uniq[0]) if end == 0 else (
            (a[-1] - a[-2]) / (uniq[-1] - uniq[-2]))
        fill[k] = a[end] + step * (missing[k] - uniq[end])
      a = np.concatenate([a, fill])
      b = np.concatenate([b, np.zeros(len(missing))])
      rms = np.concatenate([rms, np.full(len(missing), np.nan)])
      inferred_ids = set(missing.tolist())
      uniq = np.concatenate([uniq, missing])
    else:
      inferred_ids = set()
  else:
    best = None
    for mode in ('all', 'far'):  # all points vote, or only the far ones
      beam, n, _ = _clusters(sin_el, inv_r, mode, _named(sources))
      for _ in range(3):  # fit lines, reassign each point to its nearest
        a, b, rms = _fit_lines(sin_el, inv_r, beam, n)
        beam = _nearest(sin_el, inv_r, a, b, np.flatnonzero(np.isfinite(a)))
      a, b, rms = _fit_lines(sin_el, inv_r, beam, n)
      score = np.sqrt(np.mean(np.nan_to_num(rms) ** 2))
      if best is None or score < best[0]:
        best = (score, beam, n, a, b, rms)
    _, beam, n, a, b, rms = best
    uniq = np.arange(n)
    inferred_ids = set()
  top_first = np.argsort(-a, kind='stable')
  a, b, rms, uniq = a[top_first], b[top_first], rms[top_first], uniq[top_first]
  inferred = [int(i) for i, u in enumerate(uniq) if int(u) in inferred_ids]
  # Agreement: each point's nearest fitted beam against its own.
  row_of = np.empty(len(top_first), np.int64)
  row_of[top_first] = np.arange(len(top_first))
  own = row_of[beam]
  nearest = _nearest(sin_el, inv_r, a, b, np.arange(len(a)))
  firings = _firings(azimuth, own, len(a))
  _check_beams(a, own, firings, len(xyz), sources)
  if width is None:
    width = next((w for w in WIDTHS if w <= firings), max(16, firings // 16 * 16))
  offsets = b if np.max(np.abs(b)) >= OFFSET_MATTERS_M else ()
  elevation = np.rad2deg(np.arcsin(np.clip(a, -1, 1)))
  spec = SensorSpec(
      name, tuple(round(float(e), 5) for e in elevation), width=int(width),
      native_width=max(firings, int(width)),
      min_depth=float(max(0.05, np.floor(0.9 * r.min() * 100) / 100)),
      max_depth=float(max(120.0, np.ceil(1.05 * r.max()))),
      mount_height=float(mount_height),
      vertical_offset_m=tuple(round(float(v), 6) for v in offsets))
  return Estimate(spec, points=len(p), beams_measured=len(a) - len(inferred),
                  beams_inferred=inferred, rms_deg=np.rad2deg(rms),
                  agreement=float(np.mean(nearest == own)), firings=firings)
