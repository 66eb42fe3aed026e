"""Per-scan reconstruction errors of GAN inversion: the paper's Table III.

A reconstruction is what ``invert`` returns; its x_tilde is complete: every
pixel has a range, ALPHA being max_depth, not a drop.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from dusty_jax import codec
from dusty_jax.metrics import chamfer, clouds, depth as depth_metrics
from dusty_jax.sensor import SensorSpec

# (key, column title, scale) of Table III, in the paper's order.
COLUMNS = (('cd', 'CD x1e4', 1e4), ('abs_rel', 'AbsRel', 1),
           ('sq_rel', 'SqRel', 1), ('rmse', 'RMSE', 1),
           ('rmse_log', 'RMSElog', 1), ('delta1', 'd<1.25 %', 100),
           ('delta2', 'd<1.25^2 %', 100), ('delta3', 'd<1.25^3 %', 100))


def errors(target_depth, result, angles, sensor: SensorSpec,
           protocol: str = 'reference') -> dict:
  """Depth errors of x_tilde and Chamfer distance, per scan (numpy arrays).

  ``target_depth``: (B, H, W) metres (0 where no return); ``result``: the
  dict of ``invert`` (inv_depth, points, valid). The Chamfer distance is
  between the target's and the re-rendered scan's points (units of
  max_depth): ``protocol='reference'`` over their valid points only;
  ``'paper'`` as the authors' code, over all H x W pixels of both with every
  dropped pixel at the origin.
  """
  paper = clouds.check_protocol(protocol) == 'paper'
  target_depth = np.asarray(target_depth, np.float32)
  valid_t = np.asarray(codec.valid_depth(target_depth, sensor))
  pred = codec.complete_depth(result['inv_depth'], sensor)
  out = {k: np.asarray(v) for k, v in
         depth_metrics.depth_errors(pred, target_depth, valid_t).items()}
  pts_t = np.asarray(codec.to_points(np.where(valid_t, target_depth, 0.0),
                                     angles)) / sensor.max_depth
  pts_r = np.asarray(result['points']) / sensor.max_depth
  valid_r = np.asarray(result['valid'])
  cds = []
  for i in range(len(target_depth)):
    if paper:  # fixed size: one compiled shape, no (P, Q) matrix
      a = pts_t[i].reshape(1, -1, 3)
      b = np.where(valid_r[i][..., None], pts_r[i], 0.0).reshape(1, -1, 3)
      cds.append(float(chamfer.pairwise(a, b, tile=1)[0, 0]))
      continue
    a, b = pts_t[i][valid_t[i]], pts_r[i][valid_r[i]]
    cds.append(float(chamfer.chamfer(jnp.asarray(a), jnp.asarray(b)))
               if len(a) and len(b) else float('nan'))
  out['cd'] = np.array(cds)
  return out


def completion_errors(result, complete, sensor: SensorSpec) -> dict:
  """Errors of x_tilde against a simulator's complete depth (every pixel a
  perfect sensor returns, dropped or not), per scan; no Chamfer column (a
  table prints it n/a)."""
  pred = codec.complete_depth(result['inv_depth'], sensor)
  mask = np.asarray(codec.valid_depth(complete, sensor))
  out = depth_metrics.depth_errors(pred, complete, mask)
  return {k: np.asarray(v) for k, v in out.items() if k != 'count'}
