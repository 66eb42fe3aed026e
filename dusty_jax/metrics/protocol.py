"""The synthesis evaluation of Table II, reusable from code: :func:`compare`.

Both sets are (N, H, W) scans of normalised inverse depth. Each becomes
clouds in units of the sensor's max range, farthest-point sampled to
``num_points`` per cloud; then JSD, COV, MMD and 1-NNA from Chamfer
matrices of those clouds, and SWD on the inverse-depth images.

Two protocols:
  * ``'reference'`` (default): the published definitions (PointFlow,
    latent_3d_points, PGGAN); dropped pixels are never sampled, and test
    scans are taken evenly over the split (``np.linspace``).
  * ``'paper'``: what the DUSty authors' evaluation code computes, so values
    can be set beside the paper's tables: their farthest point sampling
    (pixel 0 first, nothing within 3.79 m; clouds.py), their JSD (eps bias;
    point_sets.py), their SWD (direction scaling, shifted pyramid, shared
    patch positions; swd.py) and their test subset
    ``[skip:skip * num + 1:skip]`` with ``skip = len // num`` (which gives
    num - 1 scans when num divides the split's length).
COV, MMD and 1-NNA are computed alike in both (on each protocol's clouds).
One difference of data remains: the authors' real clouds are the raw KITTI
points of each kept pixel, ours are back-projected from the range image
through the angle table (as their generated clouds are).
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from dusty_jax import codec, errors
from dusty_jax.metrics import chamfer, clouds, point_sets, swd
from dusty_jax.metrics.clouds import PROTOCOLS, check_protocol
from dusty_jax.sensor import SensorSpec, check_angles, check_spec, tiny_sensor

ROW_SCALES = (('jsd', 'JSD x1e2', 1e2), ('cov', 'COV %', 1e2),
              ('mmd', 'MMD x1e3', 1e3), ('1nna', '1-NNA %', 1e2),
              ('swd', 'SWD', 1.0))

SUBSET_RULES = {
    'reference': 'np.unique(np.linspace(0, n - 1, min(num, n)).astype(int))',
    'paper': 'skip = n // num; indices [skip:skip * num + 1:skip] of the split',
}


def evenly(n_total: int, num: int) -> np.ndarray:
  return np.unique(np.linspace(0, n_total - 1, min(num, n_total)).astype(int))


def paper_subset(n_total: int, num: int) -> np.ndarray:
  """The authors' test subset: every skip-th scan from index skip, skip =
  n_total // num, up to index skip * num (num - 1 scans when that is
  n_total)."""
  if num < 1 or num > n_total:
    raise ValueError(f'the paper\'s subset needs 1 <= num <= {n_total} (the '
                     f'split\'s size), got num={num}')
  skip = n_total // num
  return np.arange(n_total)[skip:skip * num + 1:skip]


def subset(n_total: int, num: int, protocol: str = 'reference') -> np.ndarray:
  """Indices of the evaluated scans of a split of ``n_total``."""
  if check_protocol(protocol) == 'paper':
    return paper_subset(n_total, num)
  return evenly(n_total, num)


def prepare_set(scans, angles, sensor: SensorSpec, points: int, tolerance: float = 0.0,
                protocol: str = 'reference'):
  """(B, H, W) scans -> FPS clouds (B, points, 3), full clouds, validity."""
  full, valid = clouds.scans_to_clouds(scans, angles, sensor, tolerance)
  sampled = clouds.farthest_point_sample(full, valid, points, protocol)
  return np.asarray(sampled), full, valid


def default_sensor(height: int, width: int) -> SensorSpec:
  """The depth range every preset shares (0.9 to 120 m), for scans given
  without a sensor; the metrics use only the range."""
  return dataclasses.replace(tiny_sensor(height, width),
                             name=f'default-range-{height}x{width}')


def _fingerprint(real, protocol, num_points, sensor: SensorSpec):
  return (protocol, num_points, sensor.min_depth, sensor.max_depth, real.shape,
          float(np.sum(real, dtype=np.float64)))


def compare(real, fake, angles, *, sensor: SensorSpec | None = None,
            protocol: str = 'reference', num_points: int = 2048, seed: int = 0,
            tolerance: float = 0.0, cache: dict | None = None, tile: int = 16,
            progress: bool = False) -> dict:
  """Table II's metrics between two sets of scans.

  Args:
    real: (N, H, W) reference scans, normalised inverse depth, ALPHA = -1
      for drops; finite, in float32 or float64 (NaN, inf, float16 and
      bfloat16 are refused: errors.InputError).
    fake: (N, H, W) generated scans, same encoding (as many as ``real``,
      for SWD; N >= 2, for 1-NNA's 3 clouds).
    angles: (2, H, W) elevation/azimuth table for back-projection.
    sensor: gives the depth range (default: 0.9-120 m, every preset's).
    protocol: 'reference' (published definitions) or 'paper' (the authors'
      code; see the module docstring).
    num_points: points per cloud after farthest point sampling.
    seed: SWD's random patches and directions.
    tolerance: the baseline's drop tolerance beta, applied to ``fake``.
    cache: optional dict, filled on the first call and reused by later calls
      with the same ``real`` (its clouds and Chamfer matrix); a call with
      another real set, protocol, num_points or depth range raises.
    tile: clouds per Chamfer tile.
    progress: progress bars for the Chamfer matrices.

  Returns:
    dict of floats: jsd, cov, mmd, 1nna, swd.
  """
  check_protocol(protocol)
  num_points = errors.check_count(num_points, 'num_points', low=1)
  real, fake = (np.asarray(codec.check_precision(x, what), np.float32)
                for x, what in ((real, 'real scans'), (fake, 'generated scans')))
  for x, what in ((real, 'real scans'), (fake, 'generated scans')):
    errors.check_finite(x, what, 'mark drops with ALPHA = -1, as codec.encode does')
  if real.ndim != 3 or fake.ndim != 3 or fake.shape[1:] != real.shape[1:]:
    raise ValueError('compare needs (N, H, W) scans of one shape, got '
                     f'{real.shape} and {fake.shape}')
  if len(real) != len(fake) or len(real) < 2:  # SWD pairs them; 1-NNA needs 3 clouds
    raise errors.InputError(f'compare needs as many generated scans as real ones, at least '
                            f'2 of each, got {len(real)} real and {len(fake)} generated')
  sensor = default_sensor(*real.shape[1:]) if sensor is None else check_spec(sensor)
  angles = np.asarray(angles, np.float32)
  check_angles(angles, real.shape[1:], 'scans and ')
  cache = {} if cache is None else cache
  fp = _fingerprint(real, protocol, num_points, sensor)
  if cache and cache.get('fingerprint') != fp:
    raise ValueError('this cache holds another real set or setting; pass a new dict')
  if not cache:
    ref = prepare_set(real, angles, sensor, num_points, 0.0, protocol)[0]
    cache.update(fingerprint=fp, real_clouds=ref,
                 d_rr=chamfer.pairwise(ref, tile=tile, progress=progress))
  ref, d_rr = cache['real_clouds'], cache['d_rr']
  gen = prepare_set(fake, angles, sensor, num_points, tolerance, protocol)[0]
  d_rs = chamfer.pairwise(ref, gen, tile=tile, progress=progress)
  d_ss = chamfer.pairwise(gen, tile=tile, progress=progress)
  mmd, cov = point_sets.mmd_cov(d_rs.T)
  return {
      # All point metrics on the farthest-point-sampled clouds, as the paper.
      'jsd': point_sets.jsd(ref, gen, protocol=protocol),
      'cov': cov, 'mmd': mmd,
      '1nna': point_sets.one_nna(d_rr, d_rs, d_ss),
      'swd': swd.swd(jax.random.key(seed), real, fake, protocol=protocol)['swd_mean'],
  }


def tolerance_score(m: dict) -> float:
  """The paper's weighted score for tuning the baseline's tolerance beta."""
  return m['jsd'] * 10 - m['cov'] + m['mmd'] * 1e2 + m['1nna']


def tune_tolerance(val_scans, generated, angles, sensor: SensorSpec, trials: int,
                   points: int = 512, seed: int = 0, protocol: str = 'reference') -> float:
  """The baseline's drop tolerance beta: HyperOpt TPE over [1e-3, 1e-1]
  (log-uniform) minimising :func:`tolerance_score` of ``generated`` (scans
  sampled with tolerance 0) against ``val_scans``, as in the paper."""
  try:
    import hyperopt
  except ImportError:
    raise ImportError('tuning needs hyperopt: pip install "dusty_jax[tune]"') from None
  cache = {}

  def objective(beta):
    m = compare(val_scans, generated, angles, sensor=sensor, protocol=protocol,
                num_points=points, seed=seed, tolerance=beta, cache=cache)
    return tolerance_score(m)

  best = hyperopt.fmin(objective, hyperopt.hp.loguniform('beta', np.log(1e-3), np.log(1e-1)),
                       algo=hyperopt.tpe.suggest, max_evals=trials,
                       rstate=np.random.default_rng(seed), show_progressbar=True)
  return float(best['beta'])
