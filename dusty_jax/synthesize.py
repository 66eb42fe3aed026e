"""Simulates a LiDAR dataset on procedural driving scenes.

    python -m dusty_jax.synthesize --num 1000 --out data/synthetic [--seed 0] [--sensor kitti]

Writes the prepared-array format that training reads (data/arrays.py) with
the ground truth beside it, a preview PNG, and with ``--bins`` also KITTI
``.bin`` files in sensor order.
"""

from __future__ import annotations

import argparse
import os
import sys

from dusty_jax.data import synthetic
from dusty_jax.sensor import get_sensor


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--num', type=int, required=True, help='training scans')
  parser.add_argument('--out', required=True)
  parser.add_argument('--seed', type=int, default=0)
  parser.add_argument('--sensor', default='kitti', help='sensor preset')
  parser.add_argument('--val', type=int, default=None, help='default num // 10')
  parser.add_argument('--test', type=int, default=None, help='default num // 10')
  parser.add_argument('--bins', action='store_true',
                      help='also write KITTI .bin files in sensor order')
  parser.add_argument('--workers', type=int, default=os.cpu_count() or 1)
  args = parser.parse_args(argv)
  if args.num < 1:
    sys.exit(f'error: --num must be at least 1, got {args.num}')
  try:
    sensor = get_sensor(args.sensor)
  except ValueError as e:
    sys.exit(f'error: {e}')
  small = max(args.num // 10, 1)
  splits = {'train': args.num, 'val': small if args.val is None else args.val,
            'test': small if args.test is None else args.test}
  meta = synthetic.write_dataset(args.out, sensor, args.num, args.seed,
                                 {k: v for k, v in splits.items() if v > 0},
                                 bins=args.bins, workers=args.workers)
  print(f'wrote {meta["splits"]} scans of {sensor.name} '
        f'{sensor.height}x{sensor.width} to {args.out} '
        f'(preview: {os.path.join(args.out, "preview.png")})')


if __name__ == '__main__':
  main()
