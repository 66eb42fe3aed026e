"""Reconstructs or restores scans with a trained generator (GAN inversion).

    python -m dusty_jax.tools.invert --workdir RUN --input FILE_OR_DIR \\
        [--corrupt drop:0.9|beams:8|noise:0.01] [--init random|encoder] --out DIR

RUN is a training run directory, a pretrained model's name (``--workdir
sim-dusty1``), a generator ``.npz`` or an authors' ``.pth``.

Inputs: KITTI ``.bin`` files (unfolded with the run's sensor), or ``.npy``
holding metric depth (H, W) or (N, H, W) (the prepared format). Writes per
scan ``NAME_inv_depth.npy`` (complete x_tilde), ``NAME_measurability.npy``,
``NAME_depth.npy`` (the re-rendered scan in metres), ``NAME.ply`` (its
points) and ``NAME.png`` (target, corrupted input, x_tilde, measurability,
re-rendered scan), plus ``metrics.json``. Given such a folder as --input,
only its ``NAME_depth.npy`` files are read.

    python -m dusty_jax.tools.invert --workdir RUN --split test --num 100 [--corrupt ...]
        [--protocol reference|paper] [--data_dir DIR]

evaluates over the first --num scans of a prepared split instead (of the
run's dataset, or of --data_dir: needed for a pretrained name or a single
file) and prints the layout of the paper's Table III (the authors evaluate
every test scan).
``--protocol paper`` computes the Chamfer distance as the authors' code
(every pixel of both scans, dropped ones at the origin); the default,
``reference``, over valid points only. metrics.json records the protocol,
N, seeds, the scans taken, the sensor and the dusty_jax version. Both modes
are ``evaluation.restoration``; each scan draws its corruption and its start
from its index (evaluation.RESTORE_KEYS), so --batch changes no number.
"""

from __future__ import annotations

import json
import os

import numpy as np
from absl import flags

from dusty_jax import tools


def main(argv=None):
  f = flags.FlagValues()
  flags.DEFINE_string('workdir', None, tools.model_help('the generator'),
                      flag_values=f, required=True)
  flags.DEFINE_string('input', None, '.bin/.npy file or directory', flag_values=f)
  flags.DEFINE_enum('split', None, ['train', 'val', 'test'],
                    "evaluate over this prepared split of the run's dataset instead",
                    flag_values=f)
  flags.DEFINE_integer('num', 100, 'scans of --split', lower_bound=1, flag_values=f)
  flags.DEFINE_string('data_dir', None, "a prepared dataset for --split instead of the "
                      "run's (needed for a pretrained name or a single file)",
                      flag_values=f)
  flags.DEFINE_string('corrupt', '', 'drop:F, beams:K or noise:S', flag_values=f)
  flags.DEFINE_string('out', 'inversion', 'output folder', flag_values=f)
  flags.DEFINE_integer('steps', 1000, 'optimisation steps per scan (0: the start '
                       'alone, e.g. the encoder\'s answer)', lower_bound=0, flag_values=f)
  flags.DEFINE_enum('init', 'random', ['random', 'encoder'],
                    "where the search starts: 'random' (the authors') or 'encoder' "
                    '(the run\'s encoder, from python -m dusty_jax.tools.train_encoder)',
                    flag_values=f)
  flags.DEFINE_integer('batch', 16, 'scans inverted together', lower_bound=1,
                       flag_values=f)
  flags.DEFINE_integer('seed', 0, 'random seed', flag_values=f)
  flags.register_multi_flags_validator(
      ['input', 'split'], lambda v: bool(v['input']) != bool(v['split']),
      'give exactly one of --input and --split', flag_values=f)
  flags.register_validator('corrupt', tools.valid_corruption, flag_values=f)
  flags.DEFINE_enum('protocol', 'reference', ['reference', 'paper'],
                    "Table III's Chamfer distance: 'reference' over valid points, "
                    "'paper' as the authors (dropped pixels at the origin in both)",
                    flag_values=f)
  tools.parse(f, argv, __doc__)
  tools.run(run, f)


def write_scan(stem: str, clean, target, res, sensor):
  """One restored scan's files: x_tilde, measurability, re-rendered depth,
  its points (.ply) and a picture of target, input, x_tilde, measurability
  and the re-rendered scan."""
  import trimesh
  # As run(): loaded once the flags are good.
  from dusty_jax import writers
  np.save(stem + '_inv_depth.npy', res['inv_depth'])
  np.save(stem + '_measurability.npy', res['measurability'])
  np.save(stem + '_depth.npy', res['depth'])
  trimesh.PointCloud(res['points'][res['valid']]).export(stem + '.ply')
  panels = [('clean scan', writers.DEPTH, clean), ('input scan', writers.DEPTH, target),
            ('reconstruction x_tilde', writers.DEPTH, res['inv_depth']),
            ('measurability', writers.PROBABILITY, res['measurability']),
            ('re-rendered scan', writers.DEPTH, res['scan'])]
  fig = writers.scan_figure([writers.Column(t, k, [x]) for t, k, x in panels], sensor,
                            title=os.path.basename(stem))
  writers.save_figure(fig, stem + '.png')


def run(a):
  # The library (and JAX) load once the flags are good: --help and a bad flag
  # answer at once.
  from dusty_jax import evaluation, pretrained
  from dusty_jax.data import arrays, pipeline, scan_files  # (as above)
  from dusty_jax.metrics import reconstruction, records  # (as above)

  if os.path.exists(a.out) and not os.path.isdir(a.out):
    raise ValueError(f'--out={a.out}: a file, not a folder; give a folder for the results')
  params, config = tools.load_model(a.workdir)
  if a.init == 'encoder':
    from dusty_jax import encoder  # only for this start
    encoder.check_has_encoder(params, a.workdir, pretrained.with_encoder())
  sensor = params.sensor
  truth = ring_keep = None
  if a.input:
    items = scan_files.read_scans(a.input, sensor)
    names, depth = [n for n, _ in items], np.stack([d for _, d in items])
    subset = f'every readable scan of {a.input!r}'
  else:
    if config is None and not a.data_dir:
      raise ValueError(f'{a.workdir}: no config.json naming a dataset for --split; give '
                       '--data_dir (a prepared dataset, e.g. from python -m '
                       'dusty_jax.tools.synthesize), or --input scans')
    d = a.data_dir or pipeline.dataset_dir(config, sensor, log=lambda m: None)
    depth = arrays.load_split(d, a.split, sensor)[:a.num]
    names = [f'{a.split}_{i:05d}' for i in range(len(depth))]
    truth = arrays.load_ground_truth(d, a.split, sensor, len(depth))
    if truth is not None:  # the per-ring table a measurability should beat
      ring_keep = evaluation.training_ring_keep(d, sensor)
    subset = f'the first {a.num} scans of split {a.split!r}'
  os.makedirs(a.out, exist_ok=True)

  def write(start, clean, target, res):
    for i in range(len(clean)):
      write_scan(os.path.join(a.out, names[start + i]), clean[i], target[i],
                 {k: v[i] for k, v in res.items()}, sensor)

  rec = evaluation.restoration(
      params, depth, corruption=a.corrupt, num_steps=a.steps, init=a.init,
      batch=a.batch, seed=a.seed, protocol_name=a.protocol, names=names, truth=truth,
      subset=subset, each=write if a.input else None, progress=True, ring_keep=ring_keep)
  with open(os.path.join(a.out, 'metrics.json'), 'w') as f:
    json.dump(rec, f, indent=2)
  label = f'{params.model}' + (f' ({a.corrupt})' if a.corrupt else '')
  print(f'protocol {a.protocol}: {rec["num"]} scans')
  print(records.format_table({label: rec['mean']}, reconstruction.COLUMNS))
  if 'fill' in rec:  # a corruption removed pixels: beside linear interpolation
    print('\n'.join(evaluation.fill_lines(rec['fill'])))
  if rec.get('ground_truth'):
    report_ground_truth(rec['ground_truth'], a.out)


def report_ground_truth(gt: dict, out: str):
  """Prints x_tilde's errors against the complete depth and the
  measurability's ECE; draws the reliability diagram."""
  # As run(): loaded once the flags are good.
  from dusty_jax import evaluation, writers
  from dusty_jax.metrics import reconstruction, records  # (as above)
  print(records.format_table({'x_tilde vs complete depth': gt['complete_depth']},
                             reconstruction.COLUMNS))
  print(f'measurability vs true return probability: ECE {gt["ece"]:.4f}')
  for line in evaluation.placement_lines(gt):
    print(line)
  bins = np.arange(len(gt['reliability']['pred']))
  writers.line_plot(os.path.join(out, 'reliability.png'),
                    {'measured': (bins, gt['reliability']['truth']),
                     'predicted': (bins, gt['reliability']['pred'])},
                    'bin of predicted measurability', 'return probability',
                    title=f'ECE {gt["ece"]:.4f}')


if __name__ == '__main__':
  main()
