"""What every benchmark shares: timing, the machine it ran on, result files,
pyplot for charts.

Scripts run as ``python benchmarks/X.py`` import this as a sibling module
(``import common``). JAX is imported only when a helper needs it.
"""

from __future__ import annotations

import json
import os
import platform
import runpy
import statistics
import time
from typing import Callable, NamedTuple

HERE = os.path.dirname(os.path.abspath(__file__))


# ----------------------------------------------------------------------------
# Timing.
# ----------------------------------------------------------------------------


def seconds(fn: Callable):
  """(wall seconds, result) of one call, waiting for JAX's async work."""
  import jax
  t = time.perf_counter()
  out = jax.block_until_ready(fn())
  return time.perf_counter() - t, out


class Timing(NamedTuple):
  median: float        # of ``times``
  times: list          # each timed call, s
  warmup: list         # each warm-up call (the first compiles), s
  result: object       # what the last call returned


def timed(fn: Callable, repeats: int, warmup: int = 1) -> Timing:
  """Median of ``repeats`` calls of ``fn``, after ``warmup`` calls timed apart
  (the first compiles); each call waits for its result."""
  warm = [seconds(fn)[0] for _ in range(warmup)]
  times, out = [], None
  for _ in range(repeats):
    dt, out = seconds(fn)
    times.append(dt)
  return Timing(statistics.median(times), times, warm, out)


def peak_rss_mib() -> float:
  """This process's peak resident memory, MiB: /proc's VmHWM. Not
  ru_maxrss: Linux carries a parent's peak through fork and exec into the
  child's ru_maxrss, so a subprocess's figure would be at least its parent's."""
  try:
    with open('/proc/self/status') as f:
      return next(int(l.split()[1]) for l in f if l.startswith('VmHWM:')) / 1024
  except (OSError, StopIteration):  # not Linux: ru_maxrss, in bytes on macOS
    import resource
    import sys
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == 'darwin' else peak / 1024


# ----------------------------------------------------------------------------
# The machine.
# ----------------------------------------------------------------------------


def _cpu_model() -> str:
  try:
    with open('/proc/cpuinfo') as f:
      for line in f:
        if line.startswith('model name'):
          return line.split(':', 1)[1].strip()
  except OSError:
    pass
  return platform.processor() or platform.machine()


def machine() -> dict:
  """Where a result was measured: CPU, cores, versions, devices."""
  import jax
  import jaxlib
  devices = jax.devices()
  info = dict(cpu=_cpu_model(), arch=platform.machine(), cpus=os.cpu_count(),
              python=platform.python_version(), jax=jax.__version__,
              jaxlib=jaxlib.__version__, backend=jax.default_backend(),
              device_kind=devices[0].device_kind, device_count=len(devices),
              devices=[str(d) for d in devices])
  info['banner'] = banner(info)
  return info


def banner(info: dict | None = None) -> str:
  """One line: CPU model and cores, devices, jax and jaxlib versions."""
  m = info or machine()
  return (f'{m["cpu"]} ({m["arch"]}), {m["cpus"]} CPUs; {m["device_count"]} x '
          f'{m["device_kind"]} ({m["backend"]}); jax {m["jax"]}, jaxlib {m["jaxlib"]}')


def print_banner() -> dict:
  """Prints the machine banner (at a script's start); returns machine()."""
  info = machine()
  print(info['banner'], flush=True)
  return info


# ----------------------------------------------------------------------------
# Results.
# ----------------------------------------------------------------------------


def write_json(path: str, results: dict, indent: int = 2) -> str:
  """Writes ``results`` with a ``machine`` entry (see machine()) as JSON."""
  if 'machine' in results:
    raise ValueError("results hold a 'machine' entry already")
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  with open(path, 'w') as f:
    json.dump({**results, 'machine': machine()}, f, indent=indent)
  return path


def pyplot():
  """matplotlib.pyplot on the file-only Agg backend (no display needed)."""
  import matplotlib
  matplotlib.use('Agg')
  import matplotlib.pyplot as plt
  return plt


def experiment(name: str) -> dict:
  """The globals of the repository's ``experiments/NAME.py`` (its
  ``get_config``; study.py's ``study`` and ``PRESETS``)."""
  return runpy.run_path(os.path.join(os.path.dirname(HERE), 'experiments', f'{name}.py'))
