"""Turns one of the authors' PyTorch checkpoints into a dusty_jax run directory.

    python -m dusty_jax.convert --pth dusty1_0025000000.pth [--config dusty1_config.yaml] \\
        [--data-dir data/kitti] [--angles angles.pt] [--no-ema] --workdir runs/authors_dusty1

Writes config.json, angles.npy and an orbax checkpoint whose generator and
EMA generator both hold the chosen weights (G_ema by default), so that
``load_checkpoint``, ``python -m dusty_jax.invert`` and ``python -m
dusty_jax.evaluate`` work on it. ``--data-dir`` names the prepared dataset
(``python -m dusty_jax.prepare``) that ``evaluate`` and ``invert --split``
compare with; without it they use simulated scans, which says little about a
model trained on KITTI. The angle table is, in order: ``--angles`` (a .npy or
the authors' ``angles.pt``), the prepared dataset's, the sensor's nominal one.

Their checkpoint's discriminator and optimiser states are not converted: the
run's are freshly initialised, so training on from it starts the discriminator
anew. Nothing of torch is needed (see dusty_jax/authors.py).
"""

from __future__ import annotations

import argparse
import os
import pickle
import sys


def convert(pth: str, workdir: str, config: str | None = None, ema: bool = True,
            angles: str | None = None, data_dir: str | None = None) -> str:
  """Writes the run directory ``workdir`` for an authors' checkpoint."""
  import jax
  from dusty_jax import authors, checkpoint, trainer
  from dusty_jax.data import arrays
  if os.path.exists(os.path.join(workdir, checkpoint.CONFIG_FILE)):
    raise FileExistsError(f'{workdir} already holds a run; choose another --workdir')
  if data_dir and not os.path.isdir(data_dir):
    raise FileNotFoundError(f'{data_dir}: no such dataset directory')
  params, cfg = authors.load(pth, config=config, ema=ema, angles=angles)
  if data_dir:
    cfg.data.dir = os.path.abspath(data_dir)
    if angles is None:
      params = params.replace(angles=arrays.load_angles(data_dir, params.sensor))
  setup = trainer.make_setup(cfg, params.sensor)
  state = trainer.init_state(setup, jax.random.key(0))
  state = state.replace(g_params=params.variables, ema_params=params.variables)
  checkpoint.save_config(workdir, cfg)
  checkpoint.save_angles(workdir, params.angles)
  mngr = checkpoint.manager(workdir, keep=cfg.keep_checkpoints)
  checkpoint.save(mngr, 0, state, force=True)
  mngr.wait_until_finished()
  return workdir


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--pth', required=True)
  p.add_argument('--config', default=None, help="the run's yaml (default: beside --pth)")
  p.add_argument('--angles', default=None,
                 help="(2, H, W) .npy angle table or the authors' angles.pt")
  p.add_argument('--data-dir', default=None,
                 help='prepared dataset for evaluate / invert --split (and its angles)')
  p.add_argument('--no-ema', action='store_true', help="convert 'G' instead of 'G_ema'")
  p.add_argument('--workdir', required=True)
  a = p.parse_args(argv)
  try:
    convert(a.pth, a.workdir, a.config, not a.no_ema, a.angles, a.data_dir)
  except (ValueError, KeyError, FileNotFoundError, FileExistsError,
          pickle.UnpicklingError) as e:
    sys.exit(f'error: {e}')
  print(f'wrote {a.workdir}')
  if not a.data_dir:
    print('note: no --data-dir: evaluate and invert --split will use simulated scans')


if __name__ == '__main__':
  main()
