"""restore(): fill a damaged or sparse scan's missing pixels.

    out = dusty_jax.restore(params, depth, known)              # method='auto'
    out = dusty_jax.restore(params, depth, known, method='linear')

``depth`` is metric depth, 0 where there is no return or the pixel is
missing; ``known`` says which pixels were observed (returned, or truly
dropped). Every method keeps the known returns and fills every other pixel:

  * ``'nearest'``, ``'linear'``, ``'morphological'``: the classical fills
    (interpolation.py), the baselines every restoration figure shows;
  * ``'inversion'``: the paper's: GAN inversion of the known pixels, the
    unknown ones from x_tilde; it also gives the measurability and a
    re-rendered scan with drops;
  * ``'learned'``: a small network that picks, per pixel, among the
    classical fills (restorer.py), shipped for the simulated HDL-64E;
  * ``'auto'``: the best measured for the model's sensor, else linear
    interpolation (:func:`auto_method`).

What each costs and how well it fills: benchmarks/restore.py (the README's
speed/accuracy section leads with it).
"""

from __future__ import annotations

import numpy as np

from dusty_jax import codec, errors, interpolation, restorer
from dusty_jax.data import unfolding
from dusty_jax.generator import GeneratorParams
from dusty_jax.sensor import SensorSpec

CLASSICAL = tuple(interpolation.FILLS)
METHODS = CLASSICAL + ('learned', 'inversion', 'auto')
INVERSION_STEPS = 300  # iterations of 'inversion' (the paper: 1000)


def check_inputs(params: GeneratorParams, depth, known=None):
  """(depth (B, H, W) float32, known (B, H, W) bool, single) of restore's
  inputs, or one InputError naming what is wrong."""
  if not isinstance(params, GeneratorParams):
    raise TypeError(f'params: expected a GeneratorParams (dusty_jax.load_pretrained, '
                    f'load_checkpoint), got {type(params).__name__}')
  depth = np.asarray(depth)
  if depth.dtype.kind not in 'fiu':
    raise errors.InputError(f'depth of dtype {depth.dtype}: expected metres as numbers')
  if depth.ndim not in (2, 3):
    raise errors.InputError(f'depth of shape {depth.shape}: expected (H, W) or (B, H, W) '
                            'metres')
  single = depth.ndim == 2
  hw = tuple(params.sensor.shape)
  if depth.shape[-2:] != hw:
    raise errors.InputError(
        f"depth of shape {depth.shape} does not match the model's sensor "
        f'{params.sensor.name!r} {hw}: a scan of another sensor? Restore it with a model '
        'of its own sensor, or place it on this grid first')
  errors.check_finite(depth, 'depth', 'give 0 where there is no return or the pixel '
                      'is missing, and say which were observed with known=')
  depth = np.asarray(depth, np.float32)
  if (depth < 0).any():
    raise errors.InputError(f'depth: {int((depth < 0).sum())} negative values (the '
                            f'first {float(depth[depth < 0][0])!r}); give metres, 0 '
                            'where there is no return')
  if known is None:
    known = depth > 0
  else:
    known = np.asarray(known)
    if known.shape != depth.shape:
      raise errors.InputError(f'known of shape {known.shape} does not match depth '
                              f'{depth.shape}')
    if known.dtype != bool:
      raise errors.InputError(f'known of dtype {known.dtype}: expected bool (True where '
                              'the pixel was observed)')
  depth, known = (depth[None], known[None]) if single else (depth, known)
  returns = known & np.asarray(codec.valid_depth(depth, params.sensor))
  empty = np.flatnonzero(~returns.any(axis=(1, 2)))
  if empty.size:
    which = 'the scan has' if single else f'scans {empty.tolist()} have'
    raise errors.InputError(
        f'{which} no known return inside the sensor\'s range ({params.sensor.min_depth}'
        f'-{params.sensor.max_depth} m): nothing to restore from')
  return depth, known, single


def restore(params: GeneratorParams, depth, known=None, *, method: str = 'auto',
            key=None, num_steps: int = INVERSION_STEPS):
  """Fills the pixels of ``depth`` that are not ``known``.

  Args:
    params: a trained generator (its sensor decides the shape; 'inversion'
      uses the generator itself).
    depth: (H, W) or (B, H, W) metres, 0 where there is no return or the
      pixel is missing; NaN, inf and negative values are refused.
    known: bool, the same shape: the observed pixels (returns and true
      drops); default ``depth > 0``.
    method: a name in METHODS.
    key: 'inversion''s PRNG key (default key 0).
    num_steps: 'inversion''s iterations.

  Returns:
    dict with ``depth`` (metres at every pixel: the known returns as given,
    the rest filled; clipped to the sensor's range), ``method`` (the one
    used: 'auto' resolved) and, from 'inversion', ``measurability`` and
    ``scan`` (metres: the known pixels as given, the others re-rendered with
    the generator's sampled drops, 0 where dropped). Leading axis dropped
    for a 2-D ``depth``.
  """
  if method not in METHODS:
    raise ValueError(f'method={method!r}: known methods are {list(METHODS)}')
  depth, known, single = check_inputs(params, depth, known)
  if method == 'auto':
    method = auto_method(params)
  sensor = params.sensor
  returns = known & np.asarray(codec.valid_depth(depth, sensor))
  out = {'method': method}
  if method in CLASSICAL:
    fill = interpolation.FILLS[method]
    filled = np.stack([fill(d, k, sensor.min_depth, sensor.max_depth)
                       for d, k in zip(depth, known)])
  elif method == 'learned':
    filled = restorer.fill(learned_for(params), np.where(returns, depth, 0.0), known, sensor)
  else:
    out.update(_inversion(params, depth, known, returns, key, num_steps))
    filled = out.pop('filled')
  out['depth'] = np.where(returns, depth, filled).astype(np.float32)
  return {k: (v[0] if single and k != 'method' else v) for k, v in out.items()}


def learned_for(params: GeneratorParams) -> str:
  """The shipped restorer of the model's sensor (its path), or one
  InputError saying which sensors have one."""
  path = restorer.shipped_for(params.sensor)
  if path is None:
    raise errors.InputError(
        f"method='learned': no restorer ships for sensor {params.sensor.name!r} "
        f'{params.sensor.shape} (one ships for the simulated HDL-64E, sensor \'kitti\'); '
        "use 'linear', or train one (benchmarks/research/restoration/train_restorer.py)")
  return path


def auto_method(params: GeneratorParams) -> str:
  """The best method measured (benchmarks/restore.py, README): the learned
  fill where one ships for the model's sensor (it beat linear interpolation
  on every corruption measured), else linear interpolation (which beat every
  other method)."""
  return 'learned' if restorer.shipped_for(params.sensor) else 'linear'


def _inversion(params, depth, known, returns, key, num_steps):
  """The paper's restoration: invert the known returns (x_tilde is fitted
  to returns only, as the authors'), fill from x_tilde."""
  from dusty_jax import inversion  # JAX programs: only for this method
  scans = np.asarray(codec.encode(np.where(returns, depth, 0.0), params.sensor))
  res = inversion.invert(params, scans, mask=returns, key=key, num_steps=num_steps)
  filled = np.asarray(codec.complete_depth(res['inv_depth'], params.sensor))
  scan = np.where(known, np.where(returns, depth, 0.0), np.asarray(res['depth']))
  return {'filled': filled, 'measurability': np.asarray(res['measurability']),
          'scan': scan.astype(np.float32)}


def on_grid(depth, source: SensorSpec, target: SensorSpec):
  """A scan of a sparser sensor placed on another sensor's grid, to restore
  there: (depth, known) of ``target``'s shape.

  ``depth`` (Hs, W) or (N, Hs, W) is a scan unfolded with ``source`` (its
  rows ``source``'s beams, its width ``target``'s). Each source beam goes to
  the target row nearest in elevation, where one lies within half the
  target's beam spacing there (beams outside the target's field of view are
  left out); those rows are known (returns and drops), every other row
  unknown. Two beams on one row: the first (the upper) is kept.
  """
  depth = np.asarray(depth, np.float32)
  if depth.shape[-2:] != (source.height, target.width):
    raise errors.InputError(
        f'scan of shape {depth.shape}: expected ({source.height}, {target.width}), '
        f"{source.name!r}'s beams at {target.name!r}'s width (unfold its sweep with "
        f'sensor.with_width({target.width}))')
  el_s, el_t = source.elevation, target.elevation
  nearest_row = np.abs(el_s[:, None] - el_t[None, :]).argmin(1)
  spacing = np.abs(np.gradient(el_t)) if target.height > 1 else np.array([np.inf])
  inside = np.abs(el_s - el_t[nearest_row]) <= spacing[nearest_row] / 2
  out = np.zeros(depth.shape[:-2] + target.shape, np.float32)
  known = np.zeros(out.shape, bool)
  for i in np.flatnonzero(inside)[::-1]:  # the upper beam written last, so kept
    out[..., nearest_row[i], :] = depth[..., i, :]
    known[..., nearest_row[i], :] = True
  if not inside.any():
    raise errors.InputError(f'no beam of {source.name!r} lies within {target.name!r}\'s '
                            'field of view: nothing to place on its grid')
  return out, known


def points_on_grid(points, source: SensorSpec, target: SensorSpec, ring=None):
  """:func:`on_grid` of a sweep's points (data.read_points' output, or (N,
  >=3) x, y, z) of the ``source`` sensor, unfolded at ``target``'s width."""
  scan = unfolding.to_range_image(points, source.with_width(target.width), ring=ring)
  return on_grid(scan, source, target)
