"""How well a restoration fills what a corruption removed.

Scored only on the removed pixels that had a return in the clean scan (the
kept ones are the input, and every method keeps them), per scan:
  * ``abs_rel``, ``mae`` (metres) over those pixels;
  * ``edge_abs_rel``, ``edge_mae`` over the ones on a depth edge: a pixel
    whose depth differs by more than EDGE (relative) from one of its
    4-neighbours' returns (columns wrapped), where interpolation mixes a
    foreground and a background surface;
  * ``cd``: Chamfer distance between those pixels' points, restored and
    clean (squared, in units of max_depth as Table III): a point left
    between two surfaces is far from both;
  * ``scan_abs_rel``: AbsRel over every return of the clean scan, kept ones
    included: Table III's pixels (reconstruction.errors), to stand beside
    x_tilde's figure there.
"""

from __future__ import annotations

import numpy as np
from scipy import spatial

from dusty_jax import codec
from dusty_jax.sensor import SensorSpec

EDGE = 0.1
NAMES = ('abs_rel', 'mae', 'edge_abs_rel', 'edge_mae', 'cd', 'scan_abs_rel')


def edges(depth, sensor: SensorSpec):
  """(..., H, W) bool: returns whose depth differs by more than EDGE of
  their own from a 4-neighbour's return; columns wrap."""
  depth = np.asarray(depth, np.float32)
  valid = np.asarray(codec.valid_depth(depth, sensor))
  out = np.zeros(depth.shape, bool)
  for axis, shift in ((-1, 1), (-1, -1), (-2, 1), (-2, -1)):
    other = np.roll(depth, shift, axis)
    ok = valid & np.roll(valid, shift, axis)
    if axis == -2:  # rows do not wrap
      edge_row = 0 if shift == 1 else -1
      ok[..., edge_row, :] = False
    out |= ok & (np.abs(other - depth) > EDGE * depth)
  return out


def _chamfer(a, b):
  """Squared Chamfer distance between (P, 3) and (Q, 3) points (k-d trees)."""
  if not len(a) or not len(b):
    return float('nan')
  da, _ = spatial.cKDTree(b).query(a)
  db, _ = spatial.cKDTree(a).query(b)
  return float(np.mean(da ** 2) + np.mean(db ** 2))


def scores(restored, clean, known, angles, sensor: SensorSpec) -> dict:
  """Per-scan errors (dict of (B,) arrays, NaN where a scan has no such
  pixel) of ``restored`` metric depth (B, H, W) against the ``clean`` scan's
  returns on the pixels not ``known``."""
  restored, clean = (np.asarray(x, np.float32) for x in (restored, clean))
  known = np.asarray(known, bool)
  if restored.shape != clean.shape or known.shape != clean.shape:
    raise ValueError(f'restored {restored.shape}, clean {clean.shape} and known '
                     f'{known.shape} must have one shape')
  returns = np.asarray(codec.valid_depth(clean, sensor))
  target = returns & ~known
  on_edge = target & edges(clean, sensor)
  angles = np.asarray(angles)
  out = {k: [] for k in NAMES}
  for p, t, m, e, r in zip(restored, clean, target, on_edge, returns):
    out['scan_abs_rel'].append(float(np.mean(np.abs(p[r] - t[r]) / t[r])) if r.any()
                               else np.nan)
    for prefix, sel in (('', m), ('edge_', e)):
      err = np.abs(p[sel] - t[sel])
      out[prefix + 'abs_rel'].append(float(np.mean(err / t[sel])) if sel.any() else np.nan)
      out[prefix + 'mae'].append(float(np.mean(err)) if sel.any() else np.nan)
    pts = lambda d: np.asarray(codec.to_points(d, angles))[m] / sensor.max_depth
    out['cd'].append(_chamfer(pts(p), pts(t)))
  return {k: np.asarray(v) for k, v in out.items()}
