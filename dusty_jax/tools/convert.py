"""Turns one of the authors' PyTorch checkpoints into a dusty_jax run directory.

    python -m dusty_jax.tools.convert --pth dusty1_0025000000.pth [--config dusty1_config.yaml] \\
        [--data_dir data/kitti] [--angles angles.pt] [--noema] --workdir runs/authors_dusty1

Writes config.json, generator.json, angles.npy and an orbax checkpoint whose generator and
EMA generator both hold the chosen weights (G_ema by default), so that
``load_checkpoint`` and the invert and evaluate tools work on it. ``--data_dir`` names the prepared dataset
(``python -m dusty_jax.tools.prepare``) that ``evaluate`` and ``invert --split``
compare with; without it they use simulated scans, which says little about a
model trained on KITTI. The angle table is, in order: ``--angles`` (a .npy or
the authors' ``angles.pt``), the prepared dataset's, the sensor's nominal one.

Their checkpoint's discriminator and optimiser states are not converted: the
run's are freshly initialised, so training on from it starts the discriminator
anew. Nothing of torch is needed (see dusty_jax/authors.py).
"""

from __future__ import annotations

import os

from absl import flags

from dusty_jax import tools


def convert(pth: str, workdir: str, config: str | None = None, ema: bool = True,
            angles: str | None = None, data_dir: str | None = None) -> str:
  """Writes the run directory ``workdir`` for an authors' checkpoint."""
  # The library (and JAX) load once the flags are good: --help answers at once.
  from dusty_jax import configs, generator, trainer
  from dusty_jax.data import arrays  # (as above)
  if os.path.isdir(pth):
    raise IsADirectoryError(f"{pth}: a directory; give the authors' checkpoint file (.pth)")
  if not os.path.isfile(pth):
    raise FileNotFoundError(f'{pth}: no such file')
  if pth.endswith('.npz'):
    raise ValueError(f"{pth}: a dusty_jax generator file, not an authors' checkpoint; "
                     'load it with dusty_jax.load_checkpoint (it needs no converting)')
  if os.path.exists(os.path.join(workdir, configs.FILE)):
    raise FileExistsError(f'{workdir} already holds a run; choose another --workdir')
  if data_dir and not os.path.isdir(data_dir):
    raise FileNotFoundError(f'{data_dir}: no such dataset directory')
  params, cfg = generator.load(pth, config=config, ema=ema, angles=angles)
  if data_dir:
    cfg.data.dir = os.path.abspath(data_dir)
    if angles is None:
      params = params.replace(angles=arrays.load_angles(data_dir, params.sensor))
  trainer.init_run(workdir, cfg, params)
  return workdir


def main(argv=None):
  f = flags.FlagValues()
  flags.DEFINE_string('pth', None, "the authors' checkpoint", flag_values=f, required=True)
  flags.DEFINE_string('config', None, "the run's yaml (default: beside --pth)", flag_values=f)
  flags.DEFINE_string('angles', None, "(2, H, W) .npy angle table or the authors' angles.pt",
                      flag_values=f)
  flags.DEFINE_string('data_dir', None,
                      'prepared dataset for evaluate / invert --split (and its angles)',
                      flag_values=f)
  flags.DEFINE_boolean('ema', True, "convert 'G_ema' (--noema: 'G')", flag_values=f)
  flags.DEFINE_string('workdir', None, 'the run directory to write', flag_values=f,
                      required=True)
  tools.parse(f, argv, __doc__)
  tools.run(convert, f.pth, f.workdir, f.config, f.ema, f.angles, f.data_dir)
  print(f'wrote {f.workdir}')
  if not f.data_dir:
    print('note: no --data_dir: evaluate and invert --split will use simulated scans')


if __name__ == '__main__':
  main()
