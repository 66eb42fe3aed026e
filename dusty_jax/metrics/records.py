"""What a result file records beside its numbers, and how a table of them
prints: one owner for the provenance of every metrics.json /
evaluation.json and for the paper's table layouts (Table II's columns are
protocol.ROW_SCALES, Table III's reconstruction.COLUMNS)."""

from __future__ import annotations

import importlib.metadata

import numpy as np

from dusty_jax.metrics.clouds import check_protocol
from dusty_jax.metrics.protocol import ROW_SCALES
from dusty_jax.sensor import SensorSpec, check_spec

# Result files written before the metric was named '1nna' call it 'nna'.
_LEGACY_KEYS = {'1nna': 'nna'}


def finite(values) -> np.ndarray:
  """The finite values of a column, as float64 (None counts as missing)."""
  v = np.asarray([np.nan] if values is None else values, np.float64).ravel()
  return v[np.isfinite(v)]


def finite_mean(values):
  """The mean of the finite values, or None where there is none (a table
  prints n/a; JSON holds null): a scan without a valid point has no Chamfer
  distance, and a mean must not turn NaN for it."""
  v = finite(values)
  return float(v.mean()) if v.size else None


def version() -> str:
  """dusty_jax's installed version (an editable install's is its
  pyproject.toml's at install time)."""
  try:
    return importlib.metadata.version('dusty_jax')
  except importlib.metadata.PackageNotFoundError:
    return 'unknown'


def sensor_record(sensor: SensorSpec) -> dict:
  return {'height': check_spec(sensor).height, **sensor.to_dict()}


def provenance(protocol: str, num: int, points, seeds, subset_rule: str,
               sensor: SensorSpec, **extra) -> dict:
  """What every result file records beside its numbers."""
  return {'protocol': check_protocol(protocol), 'num': int(num), 'points': points,
          'seeds': seeds, 'subset': subset_rule, 'sensor': sensor_record(sensor),
          'dusty_jax_version': version(), **extra}


def format_table(rows: dict, columns=ROW_SCALES) -> str:
  """{label: {metric: value or [values over seeds]}} -> a table in the
  paper's layout (Table II by default; reconstruction.COLUMNS for Table
  III): mean +- std where there are several values. A metric a row lacks,
  or holds only as None or NaN, prints n/a, never nan."""
  width = 18 if columns is ROW_SCALES else 12
  lw = max([24] + [len(label) + 1 for label in rows])  # labels never run into the numbers
  head = f'{"":{lw}s}' + ''.join(f'{n:>{width}s}' for _, n, _ in columns)
  lines = [head, '-' * len(head)]
  for label, m in rows.items():
    cells = []
    for k, _, s in columns:
      v = finite(m.get(k, m.get(_LEGACY_KEYS.get(k)))) * s
      cells.append('n/a' if not v.size else
                   f'{v.mean():10.3f} +- {v.std():5.3f}' if v.size > 1
                   else f'{v.mean():{width}.3f}')
    lines.append(f'{label:{lw}s}' + ''.join(f'{c:>{width}s}' for c in cells))
  return '\n'.join(lines)
