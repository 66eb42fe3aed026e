"""Test setup: 4 host CPU devices so the multi-device path always runs."""

import os

# Tests compile many small programs and run each briefly: XLA's backend
# optimisation costs more than it saves there (tests/test_train_steps.py from
# a cold cache on a 2-core VM: 46 s at level 0 against 100 s). Subprocesses
# get the same flag (FAST_COMPILE) without the forced device count: the
# training command then picks its own (parallel.use_cpu_cores), the others
# run on one.
FAST_COMPILE = '--xla_backend_optimization_level=0'
os.environ['XLA_FLAGS'] = (os.environ.get('XLA_FLAGS', '') +
                           f' --xla_force_host_platform_device_count=4 {FAST_COMPILE}').strip()
os.environ.setdefault('JAX_PLATFORMS', 'cpu')
# Tests build the same small programs many times: cache compilations on disk
# (shared with the subprocesses the tests start; one folder per user, who
# owns it).
import tempfile  # noqa: E402
os.environ.setdefault('JAX_COMPILATION_CACHE_DIR', os.path.join(
    tempfile.gettempdir(), f'dusty_jax_test_xla_cache-{getattr(os, "getuid", lambda: 0)()}'))
os.environ.setdefault('JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS', '0.5')

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from dusty_jax.sensor import SensorSpec, get_sensor, tiny_sensor  # noqa: E402


@pytest.fixture
def kitti() -> SensorSpec:
  return get_sensor('kitti')


@pytest.fixture
def tiny() -> SensorSpec:
  return tiny_sensor(16, 64)


def sensor_order_points(depth: np.ndarray, sensor: SensorSpec,
                        extra_offgrid: bool = True, seed: int = 0):
  """Points of a depth image written ring by ring in KITTI sensor order.

  Each ring sweeps counter-clockwise from straight ahead; every kept pixel
  with depth > 0 gives a point at its nominal angles. With ``extra_offgrid``
  points on native columns that subsampling discards, and a farther point
  sharing each kept pixel, are added too: the unfolding must ignore both.
  """
  rng = np.random.default_rng(seed)
  h, w = sensor.shape
  stride = sensor.column_stride
  rings = []
  for row in range(h):
    el = sensor.elevation[row]
    native = np.arange(sensor.native_width)
    frac = (native + 0.5) / sensor.native_width
    az = np.pi * (1 - 2 * frac)
    # Counter-clockwise from straight ahead: azimuth 0 -> 2pi.
    order = np.argsort(np.mod(az, 2 * np.pi), kind='stable')
    pts = []
    for n in native[order]:
      col, on_grid = divmod(n, stride)
      d = depth[row, col] if on_grid == 0 else 0.0
      if on_grid == 0 and d > 0:
        if extra_offgrid:  # a farther return at the same pixel first.
          pts.append(_point(d + 5.0, el, az[n]))
        pts.append(_point(d, el, az[n]))
      elif on_grid and extra_offgrid and depth[row, col] > 0:
        pts.append(_point(rng.uniform(2, 50), el, az[n]))
    if pts:
      rings.append(np.array(pts, np.float32))
  points = np.concatenate(rings)
  refl = rng.uniform(0, 1, (len(points), 1)).astype(np.float32)
  return np.concatenate([points, refl], 1)


def _point(d, el, az):
  return (d * np.cos(el) * np.cos(az), d * np.cos(el) * np.sin(az),
          d * np.sin(el))


def random_depth(sensor: SensorSpec, seed=0, drop=0.2) -> np.ndarray:
  rng = np.random.default_rng(seed)
  d = rng.uniform(1.5, 100.0, sensor.shape).astype(np.float32)
  d[rng.uniform(size=sensor.shape) < drop] = 0.0
  return d


@pytest.fixture(scope='session')
def smoke_run(tmp_path_factory):
  """A full tiny DUSty-I run through train_and_evaluate (4 steps), shared."""
  from dusty_jax import parallel, trainer
  from train_helpers import tiny_config
  base = tmp_path_factory.mktemp('run')
  config = tiny_config(num_steps=4, checkpoint_every=2, log_every=2,
                       image_every=4, r1_every=2)
  config.data.cache = str(base / 'cache')
  config.data.num_synthetic = 40  # 4 test scans for the evaluation CLI
  # The short evaluation a training ends with, on those scans.
  config.final_eval.update(num_synthesis=4, points=64, num_invert=2, invert_steps=2)
  workdir = str(base / 'work')
  state = trainer.train_and_evaluate(config, workdir, log=lambda m: None)
  return config, workdir, parallel.to_host(state)
