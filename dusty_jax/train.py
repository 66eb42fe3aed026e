"""Trains DUSty: ``python -m dusty_jax.train --config experiments/synthetic.py``.

Any config field can be overridden, e.g. ``--config.model=dusty2``;
``--workdir`` holds checkpoints, metrics and pictures, and a run started
again in the same workdir resumes from its latest checkpoint. A mistake in
the flags or the config is one ``error:`` line (exit 2), any other error a
user's input causes one line (exit 1), Ctrl-C one line saying what a rerun
resumes from (exit 130): see cli.py. absl's log shows warnings and errors
(``--verbosity=0`` for orbax's info lines too).
"""

import os
import sys

from absl import app, flags, logging
from ml_collections import config_flags

from dusty_jax import cli, configs, errors, parallel


def _fields(c, prefix='') -> str:
  """A config's field names, groups as ``data.{dir,cache}``."""
  return ', '.join(f'{prefix}{k}.{{{_fields(v)}}}' if hasattr(v, 'keys') else f'{prefix}{k}'
                   for k, v in c.items())


CONFIG_HELP = (
    'Experiment config file: experiments/NAME.py for NAME in '
    f'{", ".join(f[:-3] for f in cli.experiment_files()) or "(experiments/ not found)"} '
    "(a relative path not found here is looked up in the repository's experiments/). "
    'Override any field with --config.FIELD=VALUE (e.g. --config.batch_size=8, '
    f'--config.data.dir=data/kitti); the fields: {_fields(configs.default())}.')

FLAGS = flags.FLAGS
config_flags.DEFINE_config_file('config', cli.find_config('experiments/synthetic.py'),
                                CONFIG_HELP, lock_config=True)
flags.DEFINE_string('workdir', 'runs/default', 'Where the run is written.')
flags.DEFINE_string('coordinator', None,
                    'host:port of process 0 for a multi-host run.')
flags.DEFINE_integer('num_processes', None, 'Processes in a multi-host run.')
flags.DEFINE_integer('process_id', None, 'This process in a multi-host run.')
flags.DEFINE_float('peer_timeout', parallel.PEER_TIMEOUT_S,
                   'Seconds without a sign of life from another process of a '
                   'multi-host run after which a process ends, saying the '
                   'checkpoint a rerun of all processes resumes from.',
                   lower_bound=1)


def main(argv):
  if len(argv) > 1:
    cli.fail(f'unexpected arguments: {argv[1:]}', cli.USAGE)
  if not FLAGS['verbosity'].present:
    logging.set_verbosity(logging.WARNING)
  try:
    cli.run(_train)
  except cli.Exit as e:
    if parallel.joined() and not errors.show_traceback():
      # Its line is printed. JAX's exit handler would wait for the other
      # processes at a shutdown barrier (for ever, if one is lost), then
      # abort with a C++ stack trace.
      sys.stdout.flush()
      sys.stderr.flush()
      os._exit(e.code)  # pylint: disable=protected-access
    raise


def _train():
  # Before JAX's first operation: several CPU devices (parallel.use_cpu_cores).
  parallel.use_cpu_cores(FLAGS.config.batch_size, FLAGS.num_processes or 1)
  parallel.initialize_distributed(FLAGS.coordinator, FLAGS.num_processes,
                                  FLAGS.process_id, FLAGS.peer_timeout)
  from dusty_jax import trainer  # after distributed init.
  trainer.train_and_evaluate(FLAGS.config, FLAGS.workdir,
                             peer_timeout=FLAGS.peer_timeout)


def _parse(argv):
  """cli.parse_flags; --help prints the flags and exits 0, as the tools'
  (absl's exits 1)."""
  if any(a in ('-h', '--help', '-help') for a in argv[1:]):
    app.usage(shorthelp=True, writeto_stdout=True, exitcode=0)
  return cli.parse_flags(argv)


if __name__ == '__main__':
  app.run(main, flags_parser=_parse)
