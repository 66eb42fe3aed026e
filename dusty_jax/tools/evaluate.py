"""Evaluates a training run with the paper's synthesis metrics (Table II).

    python -m dusty_jax.tools.evaluate --workdir RUN [--num 5000] [--points 2048] [--seeds 5]
        [--protocol reference|paper] [--split test|val]

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

from dusty_jax import evaluation, generator, tools
from dusty_jax.data import arrays, pipeline
from dusty_jax.metrics import records


def main(argv=None):
  f = flags.FlagValues()
  flags.DEFINE_string('workdir', None, 'training run directory', flag_values=f,
                      required=True)
  flags.DEFINE_integer('num', 5000, 'clouds per set', lower_bound=1, flag_values=f)
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
  if not os.path.isdir(a.workdir):
    raise ValueError(f'{a.workdir}: evaluation needs a run directory (its config names '
                     "the dataset; convert an authors' .pth with dusty_jax.tools.convert)")
  params, config = generator.load(a.workdir)
  if config is None:
    raise ValueError(f'{a.workdir}: no config.json, so no dataset to evaluate against')
  sensor = params.sensor
  d = pipeline.dataset_dir(config, sensor, log=print)
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
  out = os.path.join(a.workdir, 'evaluation.json' if a.split == 'test' else
                     f'evaluation_{a.split}.json')
  with open(out, 'w') as f:
    json.dump(rec, f, indent=2)
  print(f'saved {out}')


if __name__ == '__main__':
  main()
