"""Turns a dataset folder into prepared arrays (see data/arrays.py).

    python -m dusty_jax.tools.prepare --dataset kitti --root /data/kitti --out data/kitti
    python -m dusty_jax.tools.prepare --dataset files --root /data/mine --pattern '*.pcd' \
        --sensor vlp16 --out data/mine        # or --sensor my_lidar.json, or --sensor auto
    python -m dusty_jax.tools.prepare --dataset files --root /data/bags --sensor vlp16 \
        --topic /velodyne_points --every 5 --out data/bags

``kitti360``, ``nuscenes``: the peers' splits at 64 x 1024 and 32 x 1024
(data/kitti360.py, data/nuscenes.py). ``files``: a folder of point files of
any spinning LiDAR (KITTI .bin, nuScenes .pcd.bin, PCD, PLY, .npy, Ouster
.pcap) and recordings (ROS1 .bag, ROS2 .db3 and .mcap: every sweep of their
PointCloud2 topic a scan, pip install 'dusty_jax[ros]'; Velodyne .pcap:
every turn a scan, pip install 'dusty_jax[velodyne]'), split by file, by
ROOT/{train,val,test}.txt where they exist, else 80/10/10 by --split_seed.
The sensor spec used is written to OUT/sensor.json; train with
``--config.data.dir=OUT --config.sensor.file=OUT/sensor.json``.
One unreadable, malformed or far too sparse scan is reported and skipped, with
a count at the end (data/prepare.py); it never stops the conversion.
"""

from __future__ import annotations

import os

from absl import flags

from dusty_jax import tools
from dusty_jax.data import prepare
from dusty_jax.sensor import PRESETS, get_sensor  # (numpy only)


def main(argv=None):
  f = flags.FlagValues()
  flags.DEFINE_enum('dataset', None, sorted(prepare.READERS), 'the dataset',
                    flag_values=f, required=True)
  flags.DEFINE_string('root', None, 'dataset root folder', flag_values=f, required=True)
  flags.DEFINE_string('out', None, 'output folder', flag_values=f, required=True)
  flags.DEFINE_list('splits', list(prepare.SPLITS), 'splits to prepare', flag_values=f)
  flags.DEFINE_string('sensor', '', 'a sensor preset, a sensor spec JSON file, or auto '
                      '(estimated from the training files); default the dataset\'s own '
                      f'({", ".join(f"{k}: {v}" for k, v in prepare.DATASET_SENSOR.items())}; '
                      'files needs one)', flag_values=f)
  flags.DEFINE_string('pattern', '*', 'files: which file names (a glob)', flag_values=f)
  flags.DEFINE_integer('split_seed', 0, 'files: the seed of the 80/10/10 split',
                       flag_values=f)
  flags.DEFINE_string('topic', None, 'files: the PointCloud2 topic of the recordings '
                      '(default the only one)', flag_values=f)
  flags.DEFINE_integer('every', 1, 'files: keep every N-th sweep of a recording (5 makes '
                       'a 10 Hz recording 2 scans a second)', lower_bound=1, flag_values=f)
  flags.register_validator(
      'sensor', lambda v: v in ('', 'auto') or v in PRESETS or os.path.isfile(v),
      f'a sensor preset ({", ".join(sorted(PRESETS))}), an existing sensor spec file, or auto',
      flag_values=f)
  flags.register_validator(
      'splits', lambda v: set(v) <= set(prepare.SPLITS),
      f'each split is one of {", ".join(prepare.SPLITS)}', flag_values=f)
  tools.parse(f, argv, __doc__)
  auto = f.sensor == 'auto'
  sensor = tools.run(get_sensor, f.sensor) if f.sensor and not auto else None
  meta = tools.run(lambda: prepare.prepare(
      f.dataset, f.root, f.out, sensor, tuple(f.splits), pattern=f.pattern,
      split_seed=f.split_seed, topic=f.topic, every=f.every, auto_sensor=auto))
  skipped = sum(len(v) for v in meta['skipped'].values())
  print(f'done: {meta["splits"]} -> {f.out}; {skipped} files skipped')


if __name__ == '__main__':
  main()
