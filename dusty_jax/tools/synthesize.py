"""Simulates a LiDAR dataset on procedural driving scenes.

    python -m dusty_jax.tools.synthesize --num 1000 --out data/synthetic [--seed 0] [--sensor kitti]

Writes the prepared-array format that training reads (data/arrays.py) with
the ground truth beside it, a preview PNG, and with ``--bins`` also KITTI
``.bin`` files in sensor order.
"""

from __future__ import annotations

import os

from absl import flags

from dusty_jax import tools
from dusty_jax.sensor import PRESETS, get_sensor  # (numpy only)


def main(argv=None):
  f = flags.FlagValues()
  flags.DEFINE_integer('num', None, 'training scans', lower_bound=1, flag_values=f,
                       required=True)
  flags.DEFINE_string('out', None, 'output folder', flag_values=f, required=True)
  flags.DEFINE_integer('seed', 0, 'scene seed', flag_values=f)
  flags.DEFINE_string('sensor', 'kitti', f'a sensor preset ({", ".join(sorted(PRESETS))}) '
                      'or a sensor spec JSON file', flag_values=f)
  flags.register_validator(
      'sensor', lambda v: v in PRESETS or os.path.isfile(v),
      f'a sensor preset ({", ".join(sorted(PRESETS))}) or an existing sensor spec file',
      flag_values=f)
  flags.DEFINE_integer('val', None, 'validation scans (default num // 10)',
                       lower_bound=0, flag_values=f)
  flags.DEFINE_integer('test', None, 'test scans (default num // 10)', lower_bound=0,
                       flag_values=f)
  flags.DEFINE_boolean('bins', False, 'also write KITTI .bin files in sensor order',
                       flag_values=f)
  flags.DEFINE_integer('workers', os.cpu_count() or 1, 'processes', lower_bound=1,
                       flag_values=f)
  tools.parse(f, argv, __doc__)
  sensor = tools.run(get_sensor, f.sensor)
  # The simulator (and JAX) load once the flags are good: --help answers at once.
  from dusty_jax.data import synthetic
  small = max(f.num // 10, 1)
  splits = {'train': f.num, 'val': small if f.val is None else f.val,
            'test': small if f.test is None else f.test}
  meta = tools.run(lambda: synthetic.write_dataset(
      f.out, sensor, f.num, f.seed, {k: v for k, v in splits.items() if v > 0},
      bins=f.bins, workers=f.workers))
  print(f'wrote {meta["splits"]} scans of {sensor.name} '
        f'{sensor.height}x{sensor.width} to {f.out} '
        f'(preview: {os.path.join(f.out, "preview.png")})')


if __name__ == '__main__':
  main()
