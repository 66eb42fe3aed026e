"""README.md's example runs as written, so the README cannot drift from the
library. The block between ``<!-- example -->`` and
``<!-- /example -->`` is run in a fresh process in a temporary directory,
with its step counts made small; nothing else of it is changed."""

import os
import re
import subprocess
import sys

import numpy as np
from PIL import Image
import pytest

from conftest import FAST_COMPILE

REPO = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..')


def example() -> str:
  """The Python code of README.md's example block."""
  text = open(os.path.join(REPO, 'README.md')).read()
  found = re.search(r'<!-- example -->\s*```python\n(.*?)```\s*<!-- /example -->', text,
                    re.S)
  assert found, 'README.md has no ```python block between <!-- example --> markers'
  return found.group(1)


def test_the_example_block_is_found_and_shows_every_step():
  """The example loads a shipped model, encodes scans, inverts them from a
  random start and from the encoder, and saves a picture."""
  code = example()
  for call in ("load_pretrained('sim-dusty1')", 'codec.encode(', "init='encoder'",
               'dusty_jax.invert(params, scans, num_steps=', 'savefig('):
    assert call in code, call


@pytest.mark.slow
def test_the_readme_example_runs(tmp_path):
  code, n = re.subn(r'num_steps=\d+', 'num_steps=3', example())
  assert n == 2  # the search from a random start and the one from the encoder
  script = tmp_path / 'example.py'
  script.write_text(code)
  env = dict(os.environ, XLA_FLAGS=FAST_COMPILE, MPLBACKEND='Agg',
             PYTHONPATH=os.path.abspath(REPO))
  r = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env,
                     capture_output=True, text=True, timeout=900)
  assert r.returncode == 0, r.stderr[-3000:]
  losses = [float(x) for x in re.findall(r'masked L1 ([\d.]+)', r.stdout)]
  assert len(losses) == 2 and all(0 < x < 1 for x in losses), r.stdout
  pictures = [p for p in os.listdir(tmp_path) if p.endswith('.png')]
  assert pictures, 'the example saved no picture'
  image = np.asarray(Image.open(tmp_path / pictures[0]).convert('L'))
  assert image.shape[0] > 100 and image.std() > 1  # drawn, not blank


def own_lidar_block() -> str:
  """The shell commands of README.md's "Your own LiDAR" section."""
  text = open(os.path.join(REPO, 'README.md')).read()
  found = re.search(r'<!-- own-lidar -->\s*```sh\n(.*?)```\s*<!-- /own-lidar -->', text, re.S)
  assert found, 'README.md has no ```sh block between <!-- own-lidar --> markers'
  return found.group(1)


@pytest.mark.slow
def test_the_own_lidar_commands_run(tmp_path):
  """The spec file, the prepare command and both trainings run as written,
  with the smoke networks and two steps (the only changes); the run records
  the spec, so it loads once the file is gone."""
  import json
  from dusty_jax import generator, sensor as sensor_lib
  from dusty_jax.data import points, simulated_lidar
  block = own_lidar_block()
  commands = [c for c in re.split(r'\n(?=python |echo )', block.strip()) if c.strip()]
  assert [c.split()[0] for c in commands] == ['echo', 'python', 'python', 'python']
  # The spec the block writes, to simulate the folder of sweeps it prepares.
  spec_json = re.search(r"echo '(.*?)' > my16.json", block, re.S).group(1)
  spec = sensor_lib.SensorSpec.from_dict(json.loads(spec_json))
  for seed in range(10):
    depth = simulated_lidar.render_scan(seed, spec).depth
    hit = depth > 0
    xyz = (depth[..., None] * simulated_lidar.ray_directions(spec))[hit]
    points.write_points(str(tmp_path / 'sweeps' / f'{seed:03d}.ply'),
                        {'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2],
                         'ring': np.nonzero(hit)[0].astype(np.uint16)})
  smoke = os.path.join(REPO, 'experiments', 'smoke.py')
  fast = (' --config.num_steps=2 --config.checkpoint_every=2 --config.sensor.width=0'
          ' --config.data.num_synthetic=16')
  env = dict(os.environ, XLA_FLAGS=FAST_COMPILE, MPLBACKEND='Agg',
             PYTHONPATH=os.path.abspath(REPO), DUSTY_JAX_CACHE=str(tmp_path / 'cache'))
  for command in commands:
    if 'dusty_jax.train' in command:
      command = command.replace('experiments/synthetic.py', smoke) + fast
    r = subprocess.run(['bash', '-c', command], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=900)
    assert r.returncode == 0, (command, r.stderr[-3000:])
  assert sensor_lib.load(str(tmp_path / 'data/my16/sensor.json')) == spec
  os.remove(tmp_path / 'my16.json')
  for run in ('runs/my16_sim', 'runs/my16'):
    assert generator.read_spec(str(tmp_path / run))[0] == spec
