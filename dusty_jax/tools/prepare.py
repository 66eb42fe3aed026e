"""Turns a KITTI or MPO folder into prepared arrays (see data/arrays.py).

    python -m dusty_jax.tools.prepare --dataset kitti --root /data/kitti --out data/kitti

One unreadable, malformed or far too sparse scan is reported and skipped, with
a count at the end (data/prepare.py); it never stops the conversion.
"""

from __future__ import annotations

from absl import flags

from dusty_jax import tools
from dusty_jax.data import prepare


def main(argv=None):
  f = flags.FlagValues()
  flags.DEFINE_enum('dataset', None, sorted(prepare.READERS), 'the dataset',
                    flag_values=f, required=True)
  flags.DEFINE_string('root', None, 'dataset root folder', flag_values=f, required=True)
  flags.DEFINE_string('out', None, 'output folder', flag_values=f, required=True)
  flags.DEFINE_list('splits', list(prepare.SPLITS), 'splits to prepare', flag_values=f)
  flags.register_validator(
      'splits', lambda v: set(v) <= set(prepare.SPLITS),
      f'each split is one of {", ".join(prepare.SPLITS)}', flag_values=f)
  tools.parse(f, argv, __doc__)
  meta = tools.run(prepare.prepare, f.dataset, f.root, f.out, None, tuple(f.splits))
  skipped = sum(len(v) for v in meta['skipped'].values())
  print(f'done: {meta["splits"]} -> {f.out}; {skipped} files skipped')


if __name__ == '__main__':
  main()
