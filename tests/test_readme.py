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
