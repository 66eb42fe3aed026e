"""The paper's synthesis evaluation protocol (Table II), reusable from code.

Reference clouds: ``num`` scans evenly spaced over the test split. For each
seed, ``num`` scans are sampled from the EMA generator. Both sides become
clouds in units of 120 m (dropped pixels excluded), farthest-point sampled
to ``points`` per cloud; then JSD, COV, MMD and 1-NNA from Chamfer matrices,
and SWD on the inverse-depth images.
"""

from __future__ import annotations

import numpy as np

from dusty_jax.metrics import chamfer, clouds, point_sets, swd

ROW_SCALES = (('jsd', 'JSD x1e2', 1e2), ('cov', 'COV %', 1e2),
              ('mmd', 'MMD x1e3', 1e3), ('nna', '1-NNA %', 1e2),
              ('swd', 'SWD', 1.0))


def evenly(n_total: int, num: int) -> np.ndarray:
  return np.unique(np.linspace(0, n_total - 1, min(num, n_total)).astype(int))


def prepare_set(scans, angles, sensor, points: int, tolerance: float = 0.0):
  """(B, H, W) scans -> FPS clouds (B, points, 3), full clouds, validity."""
  full, valid = clouds.scans_to_clouds(scans, angles, sensor, tolerance)
  return np.asarray(clouds.farthest_point_sample(full, valid, points)), full, valid


def compare(ref_scans, gen_scans, angles, sensor, points: int, key,
            tolerance_gen: float = 0.0, d_rr=None, ref=None, tile: int = 16,
            progress: bool = False):
  """All metrics between reference and generated scans; returns (dict, cache).

  ``d_rr`` and ``ref`` (the reference clouds) may be passed back in to reuse
  them across seeds.
  """
  if ref is None:
    ref = prepare_set(ref_scans, angles, sensor, points)
  gen = prepare_set(gen_scans, angles, sensor, points, tolerance_gen)
  if d_rr is None:
    d_rr = chamfer.pairwise(ref[0], tile=tile, progress=progress)
  d_rs = chamfer.pairwise(ref[0], gen[0], tile=tile, progress=progress)
  d_ss = chamfer.pairwise(gen[0], tile=tile, progress=progress)
  mmd, cov = point_sets.mmd_cov(d_rs.T)
  out = {
      # All point metrics on the farthest-point-sampled clouds, as the paper.
      'jsd': point_sets.jsd(ref[0], gen[0]),
      'cov': cov, 'mmd': mmd,
      'nna': point_sets.one_nna(d_rr, d_rs, d_ss),
      'swd': swd.swd(key, ref_scans, gen_scans)['swd_mean'],
  }
  return out, (d_rr, ref)


def format_table(rows: dict) -> str:
  """{label: {metric: [values over seeds]}} -> Table II layout, mean +- std."""
  head = f'{"":24s}' + ''.join(f'{n:>18s}' for _, n, _ in ROW_SCALES)
  lines = [head, '-' * len(head)]
  for label, m in rows.items():
    cells = []
    for k, _, s in ROW_SCALES:
      v = np.asarray(m[k], np.float64) * s
      cells.append(f'{v.mean():10.3f} +- {v.std():5.3f}' if len(v) > 1
                   else f'{v.mean():18.3f}')
    lines.append(f'{label:24s}' + ''.join(f'{c:>18s}' for c in cells))
  return '\n'.join(lines)


def tolerance_score(m: dict) -> float:
  """The paper's weighted score for tuning the baseline's tolerance beta."""
  return m['jsd'] * 10 - m['cov'] + m['mmd'] * 1e2 + m['nna']
