"""Simulated-LiDAR speed: ms per 64x256 scan on one core, and scans/s overall.

    python benchmarks/synthesize.py [--num 200] [--workers 2]

Reports scene building and ray casting separately (median over --num scans,
one process), then the throughput of ``simulate`` with --workers processes,
and the time 10,000 scans take at that rate.
"""

import argparse
import os
import statistics

import numpy as np

import common
from dusty_jax.data import scene, simulated_lidar, synthetic
from dusty_jax.sensor import get_sensor


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--num', type=int, default=200)
  p.add_argument('--workers', type=int, default=os.cpu_count() or 1)
  p.add_argument('--out', default=os.path.join(os.path.dirname(__file__), 'results',
                                               'synthesize.json'))
  a = p.parse_args()
  common.print_banner()
  sensor = get_sensor('kitti')
  dirs = simulated_lidar.ray_directions(sensor).reshape(-1, 3)
  build, cast, total = [], [], []
  for i in range(a.num):
    dt, (mesh, _, _) = common.seconds(lambda: scene.build_scene(i))
    build.append(dt)
    cast.append(common.seconds(lambda: simulated_lidar.intersector(mesh).intersects_id(
        np.zeros_like(dirs), dirs, multiple_hits=False, return_locations=True))[0])
    total.append(common.seconds(lambda: simulated_lidar.render_scan(i, sensor))[0])
  rays = len(dirs) / statistics.median(cast)
  print(f'embree: {simulated_lidar.has_embree()}; one core, median of {a.num} scans: '
        f'build {statistics.median(build) * 1e3:.1f} ms, cast {statistics.median(cast) * 1e3:.1f} ms '
        f'({rays / 1e6:.2f} M rays/s incl. BVH build), whole scan '
        f'{statistics.median(total) * 1e3:.1f} ms')
  dt, _ = common.seconds(lambda: synthetic.simulate(a.num, sensor, seed=1, progress=False,
                                                   workers=a.workers))
  rate = a.num / dt
  print(f'simulate, {a.workers} workers: {rate:.1f} scans/s -> 10,000 scans in '
        f'{10000 / rate / 60:.1f} min')
  common.write_json(a.out, dict(
      embree=simulated_lidar.has_embree(), build_ms=statistics.median(build) * 1e3,
      cast_ms=statistics.median(cast) * 1e3, scan_ms=statistics.median(total) * 1e3,
      workers=a.workers, scans_per_s=rate, minutes_per_10k=10000 / rate / 60,
      cpus=os.cpu_count()))


if __name__ == '__main__':
  main()
