"""Reading and unfolding one sweep of ~100k points in each format, on one core.

    python benchmarks/read_points.py [--points 100000] [--repeats 15]

A simulated sweep (float32 x, y, z, intensity; uint16 ring; uint8
return_type; float64 time_stamp: a VLP-16 driver's fields) is written once
per format with data.write_points, then read with data.read_points: the
first read (an Ouster recording's builds the SDK's XYZ table, kept for the
next) and the median of ``--repeats`` more, in this one process pinned to
one CPU. The Ouster sample recording (../shared, 128 x 1024
pixels, ~107k returns; needs ouster-sdk) is read as it is, where present.
Each read sweep is then unfolded into the VLP-16 preset's 16 x 1024 image
(the Ouster recording into its own calibration's 128 x 1024) with its ring
field and without (rows by elevation): median of ``--repeats``. The
target: reading and unfolding 100k points under 50 ms on one core. Prints a
table and writes benchmarks/results/read_points.json
(``--out``).
"""

import argparse
import os
import statistics
import tempfile
import time

import numpy as np

import common
from dusty_jax import sensor as sensor_lib
from dusty_jax.data import read_points, ring_field, unfolding, write_points
from dusty_jax.errors import UserError

HERE = os.path.dirname(os.path.abspath(__file__))
OUSTER_PCAP = os.path.join(HERE, '..', '..', 'shared', 'data', 'sensors-sample',
                           'OS-1-128_v2.3.0_1024x10_lb_n3.pcap')
OUSTER_JSON = OUSTER_PCAP.replace('_lb_n3.pcap', '.json')

# (label, file name, encoding) of each format timed.
FORMATS = [
    ('KITTI .bin', 'sweep.bin', None),
    ('nuScenes .pcd.bin', 'sweep.pcd.bin', None),
    ('PCD binary', 'binary.pcd', 'binary'),
    ('PCD binary_compressed', 'compressed.pcd', 'binary_compressed'),
    ('PCD ascii', 'ascii.pcd', 'ascii'),
    ('PLY binary', 'binary.ply', 'binary'),
    ('PLY ascii', 'ascii.ply', 'ascii'),
    ('.npy structured', 'structured.npy', None),
]


def sweep(n: int, seed: int = 0) -> dict:
  """A 16-ring sweep of n points at 1-80 m with a driver's fields."""
  rng = np.random.default_rng(seed)
  ring = rng.integers(0, 16, n).astype(np.uint16)
  elevation = np.deg2rad(-15 + 2 * ring.astype(np.float64))
  azimuth = rng.uniform(-np.pi, np.pi, n)
  r = rng.uniform(1, 80, n)
  return {
      'x': (r * np.cos(elevation) * np.cos(azimuth)).astype(np.float32),
      'y': (r * np.cos(elevation) * np.sin(azimuth)).astype(np.float32),
      'z': (r * np.sin(elevation)).astype(np.float32),
      'intensity': rng.uniform(0, 255, n).astype(np.float32),
      'ring': ring,
      'return_type': rng.integers(0, 3, n).astype(np.uint8),
      'time_stamp': 1.67e9 + rng.uniform(0, 0.1, n),
  }


def _median_ms(fn, repeats: int) -> float:
  times = []
  for _ in range(repeats):
    t = time.perf_counter()
    fn()
    times.append(1e3 * (time.perf_counter() - t))
  return statistics.median(times)


def time_reads(path: str, repeats: int, sensor) -> dict:
  """The first read (ms), then median, min and max of ``repeats`` more; points
  read; the median unfolding with and without the ring field."""
  t = time.perf_counter()
  fields = read_points(path)
  first = 1e3 * (time.perf_counter() - t)
  times = []
  for _ in range(repeats):
    t = time.perf_counter()
    read_points(path)
    times.append(1e3 * (time.perf_counter() - t))
  ring = ring_field(fields)
  unfold_ring = _median_ms(lambda: unfolding.unfold(fields, sensor, ring=ring), repeats)
  unfold_bare = _median_ms(lambda: unfolding.unfold(fields, sensor), repeats)
  return {'first_ms': first, 'median_ms': statistics.median(times), 'min_ms': min(times), 'max_ms': max(times),
          'points': int(len(fields['x'])), 'bytes': os.path.getsize(path),
          'unfold_ring_ms': unfold_ring, 'unfold_no_ring_ms': unfold_bare,
          'read_and_unfold_ms': statistics.median(times) + max(unfold_ring, unfold_bare)}


def main():
  ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  ap.add_argument('--points', type=int, default=100_000)
  ap.add_argument('--repeats', type=int, default=15)
  ap.add_argument('--out', default=os.path.join(HERE, 'results', 'read_points.json'))
  args = ap.parse_args()
  if hasattr(os, 'sched_setaffinity'):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})  # one core
  load = os.getloadavg()
  print(f'load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; one core; '
        f'{args.points} points; median of {args.repeats} reads', flush=True)
  fields = sweep(args.points)
  results = {}
  with tempfile.TemporaryDirectory() as d:
    for label, name, encoding in FORMATS:
      path = os.path.join(d, name)
      try:
        write_points(path, fields, encoding=encoding)
      except UserError as e:  # an optional reader missing
        print(f'{label:24s} skipped: {e}')
        continue
      results[label] = time_reads(path, args.repeats, sensor_lib.PRESETS['vlp16'])
  if os.path.exists(OUSTER_PCAP):
    try:
      results['Ouster .pcap (sample)'] = time_reads(
          OUSTER_PCAP, args.repeats, sensor_lib.from_ouster_metadata(OUSTER_JSON))
    except UserError as e:
      print(f'{"Ouster .pcap (sample)":24s} skipped: {e}')
  print(f'{"format":24s} {"points":>8s} {"MB":>6s} {"first ms":>9s} {"read ms":>8s} '
        f'{"min":>7s} {"max":>7s} {"unfold ring":>12s} {"no ring":>8s} {"read+unfold":>12s}')
  for label, r in results.items():
    print(f'{label:24s} {r["points"]:8d} {r["bytes"] / 1e6:6.2f} {r["first_ms"]:9.2f} '
          f'{r["median_ms"]:8.2f} {r["min_ms"]:7.2f} {r["max_ms"]:7.2f} '
          f'{r["unfold_ring_ms"]:12.2f} {r["unfold_no_ring_ms"]:8.2f} '
          f'{r["read_and_unfold_ms"]:12.2f}')
  common.write_json(args.out, {'points': args.points, 'repeats': args.repeats,
                               'load_average': load, 'formats': results,
                               'command': f'python benchmarks/read_points.py --points '
                                          f'{args.points} --repeats {args.repeats}'})
  print('wrote', args.out)


if __name__ == '__main__':
  main()
