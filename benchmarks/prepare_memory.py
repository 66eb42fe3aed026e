"""Peak memory of prepare (and of the training loader) against the number of scans.

    python benchmarks/prepare_memory.py [--nums 200,20000] [--points 32] [--tree DIR]

Writes small synthetic KITTI ``.bin`` scans (64 rings x --points returns,
sensor order) into a temporary dataset root, runs
``dusty_jax.data.prepare.prepare`` on its training split in a fresh
subprocess per size, and reads the subprocess's peak resident set
(``common.peak_rss_mib``: a subprocess's ``ru_maxrss`` would count its parent's).
Then, on each prepared array, draws 100 training batches of 32 with the
train loader (``data.pipeline.Batches``, memory-mapped) in another
subprocess, and reads its peak too, and its private (anonymous) resident
memory: pages of the memory-mapped array it touched count in the peak but
are the kernel's page cache, reclaimable. ``--tree`` runs the dusty_jax of
another checkout (e.g. the code before prepare wrote scan by scan) for a
comparison. Results: benchmarks/results/prepare_memory.json.
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

import common
from dusty_jax.data import kitti
from dusty_jax.sensor import get_sensor

# Each runs in a subprocess of its own, on --tree's dusty_jax; ``common`` is
# this directory's (run puts it on the path after the tree).
PREPARE = '''
import sys
import common
from dusty_jax.data import prepare
meta = prepare.prepare('kitti', sys.argv[1], sys.argv[2], splits=('train',),
                       log=lambda m: None)
print(meta['splits']['train'], common.peak_rss_mib())
'''

LOADER = '''
import sys
import common
from dusty_jax.data import arrays, pipeline
from dusty_jax.sensor import get_sensor
sensor = get_sensor('kitti')
depth = arrays.load_split(sys.argv[1], 'train', sensor)
batches = pipeline.Batches(depth, sensor, 32, seed=0)
for step in range(100):
  batches(step)
status = dict(l.split(':', 1) for l in open('/proc/self/status'))
anon = int(status.get('RssAnon', '0 kB').split()[0])
print(anon, len(depth), common.peak_rss_mib())
'''


def write_scans(root: str, num: int, points: int, seed: int = 0):
  """``num`` scans of ``points`` returns per ring, in KITTI sensor order
  (each ring counter-clockwise from straight ahead), at random depths."""
  sensor = get_sensor('kitti')
  rng = np.random.default_rng(seed)
  el = np.radians(np.asarray(sensor.elevation, np.float64))[:, None]
  az = 2 * np.pi * (np.arange(points) + 0.5) / points
  az = np.where(az > np.pi, az - 2 * np.pi, az)[None, :]
  d = os.path.join(root, 'sequences', '00', 'velodyne')
  os.makedirs(d, exist_ok=True)
  for i in range(num):
    r = rng.uniform(3.0, 80.0, (sensor.height, points))
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                    r * np.sin(el) * np.ones_like(az)], -1).reshape(-1, 3)
    kitti.write_bin(os.path.join(d, f'{i:06d}.bin'), xyz)


def run(code: str, args, tree: str):
  env = dict(os.environ, PYTHONPATH=os.pathsep.join([tree, common.HERE]), JAX_PLATFORMS='cpu')
  t = time.time()
  res = subprocess.run([sys.executable, '-c', code] + list(args), env=env, cwd=tree,
                       capture_output=True, text=True)
  if res.returncode:
    raise SystemExit(f'failed:\n{res.stderr[-3000:]}')
  *extra, count, peak_mib = res.stdout.split()
  return int(count), float(peak_mib), time.time() - t, [int(x) / 1024 for x in extra]


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--nums', default='200,20000')
  p.add_argument('--points', type=int, default=32, help='returns per ring')
  p.add_argument('--tree', default=os.path.dirname(os.path.dirname(os.path.abspath(
      __file__))), help='the dusty_jax checkout to measure')
  p.add_argument('--out', default=os.path.join(os.path.dirname(__file__), 'results',
                                               'prepare_memory.json'))
  a = p.parse_args()
  common.print_banner()
  rows = []
  with tempfile.TemporaryDirectory() as tmp:
    for num in (int(n) for n in a.nums.split(',')):
      root, out = os.path.join(tmp, f'raw{num}'), os.path.join(tmp, f'prepared{num}')
      write_scans(root, num, a.points)
      count, prep_mib, prep_s, _ = run(PREPARE, [root, out], a.tree)
      size = os.path.getsize(os.path.join(out, 'train.npy')) / 2**20
      _, load_mib, _, (anon_mib,) = run(LOADER, [out], a.tree)
      rows.append(dict(scans=count, array_mib=size, prepare_peak_rss_mib=prep_mib,
                       prepare_seconds=prep_s, loader_peak_rss_mib=load_mib,
                       loader_anon_rss_mib=anon_mib))
      print(f'{count:6d} scans ({size:7.1f} MiB array): prepare peak RSS '
            f'{prep_mib:7.1f} MiB in {prep_s:6.1f} s; train loader (100 batches of 32) '
            f'peak RSS {load_mib:7.1f} MiB, of it private (not the mapped file) '
            f'{anon_mib:7.1f} MiB at the end', flush=True)
      for d in (root, out):
        subprocess.run(['rm', '-rf', d], check=True)
  common.write_json(a.out, {'tree': a.tree, 'points_per_ring': a.points,
                            'rows': rows})


if __name__ == '__main__':
  main()
