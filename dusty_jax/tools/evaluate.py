"""Evaluates a training run with the paper's synthesis metrics (Table II).

    python -m dusty_jax.tools.evaluate --workdir RUN [--num 5000] [--points 2048] [--seeds 5]
        [--protocol reference|paper] [--split test|val] [--data_dir DIR]

RUN is a training run directory, or with ``--data_dir`` (a prepared dataset)
a pretrained model's name (``--workdir sim-dusty1``), a generator ``.npz`` or
an authors' ``.pth``; evaluation.json goes into the run, else the current
directory.

Samples from the EMA generator, compares with the test split of the run's
dataset, and prints mean +- std over seeds, with the "training set" row
(train vs test) for reference: dusty_jax/evaluation.py's ``synthesis``, the
function benchmarks call too. ``--protocol paper`` computes as the
authors' code does, test subset included (values to set beside the paper's
Table II; see dusty_jax/metrics/protocol.py); the default, ``reference``,
follows the published metric definitions. evaluation.json records the
protocol, N, points, seeds, the test-subset rule, the sensor and the
dusty_jax version. For the baseline model, ``--tune`` first tunes the
point-drop tolerance beta on the validation split with HyperOpt (TPE,
within [1e-3, 1e-1], at 512 points), minimising JSD x 10 - COV + MMD x 1e2 +
1-NNA as in the paper. ``--split val`` compares with the validation split
instead, for choosing between runs without looking at the test split; it
writes evaluation_val.json. Runs on a CPU; the full protocol (5000 clouds of 2048
points) takes hours there: see benchmarks/eval_tradeoff.py for cheaper
settings and what they cost in accuracy.
"""

from __future__ import annotations

import json
import os

from absl import flags

from dusty_jax import tools


def main(argv=None):
  f = flags.FlagValues()
  flags.DEFINE_string('workdir', None, tools.model_help('the generator') +
                      ' (a run is compared with its own dataset; anything else with '
                      '--data_dir)', flag_values=f, required=True)
  flags.DEFINE_string('data_dir', None, 'a prepared dataset to compare with instead of '
                      "the run's (needed for a pretrained name or a single file)",
                      flag_values=f)
  flags.DEFINE_integer('num', 5000, 'clouds per set', lower_bound=2, flag_values=f)
  flags.DEFINE_integer('points', 2048, 'points per cloud', lower_bound=1, flag_values=f)
  flags.DEFINE_integer('seeds', 5, 'generated sets', lower_bound=1, flag_values=f)
  flags.DEFINE_float('tolerance', None, "baseline's beta (default: the run's)",
                     flag_values=f)
  flags.DEFINE_boolean('tune', False, 'tune beta on the validation split (baseline); '
                       'saved in the run', flag_values=f)
  flags.DEFINE_integer('tune_trials', 100, 'HyperOpt trials', lower_bound=1,
                       flag_values=f)
  flags.DEFINE_boolean('train_row', True, 'also the training-set row', flag_values=f)
  flags.DEFINE_enum('protocol', 'reference', ['reference', 'paper'],
                    "'reference': published definitions; 'paper': the authors' code",
                    flag_values=f)
  flags.DEFINE_enum('split', 'test', ['test', 'val'],
                    "the split to compare with: 'val' to choose between runs",
                    flag_values=f)
  tools.parse(f, argv, __doc__)
  tools.run(run, f)


def run(a):
  # The library (and JAX) load once the flags are good: --help answers at once.
  from dusty_jax import evaluation, generator
  from dusty_jax.data import arrays, pipeline  # (as above)
  from dusty_jax.metrics import records  # (as above)
  is_run = os.path.isdir(a.workdir)
  if a.tune and not is_run:
    raise ValueError(f'{a.workdir}: --tune saves beta in a run directory; give one')
  params, config = tools.load_model(a.workdir)
  if config is None and not a.data_dir:
    raise ValueError(f'{a.workdir}: no config.json naming a dataset to evaluate against; '
                     'give --data_dir (a prepared dataset, e.g. from python -m '
                     'dusty_jax.tools.synthesize)')
  sensor = params.sensor
  d = a.data_dir or pipeline.dataset_dir(config, sensor, log=print)
  split = lambda name: arrays.load_split(d, name, sensor)
  tol = a.tolerance
  if a.tune:
    tol = evaluation.tune_tolerance(params, split('val'), num=a.num, trials=a.tune_trials,
                                    protocol_name=a.protocol)
    generator.set_tolerance(a.workdir, tol)
    print(f'tuned tolerance beta = {tol:.5f} (saved in the run: load_checkpoint '
          'now decodes with it)')
  rec = evaluation.synthesis(params, split(a.split), split('train') if a.train_row else None,
                             num=a.num, points=a.points, seeds=a.seeds,
                             protocol_name=a.protocol, tolerance=tol, progress=True)
  if rec['num'] < a.num:
    print(f'note: the {a.split} subset has {rec["num"]} scans; evaluated {rec["num"]} per set')
  rec['split'] = a.split
  print(f'protocol {a.protocol}, {a.split} split: N = {rec["num"]} clouds of {a.points} '
        f'points, {a.seeds} seeds')
  print(records.format_table(rec['rows']))
  out = os.path.join(a.workdir if is_run else '.', 'evaluation.json' if a.split == 'test'
                     else f'evaluation_{a.split}.json')
  with open(out, 'w') as f:
    json.dump(rec, f, indent=2)
  print(f'saved {out}')


if __name__ == '__main__':
  main()
