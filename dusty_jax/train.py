"""Trains DUSty: ``python -m dusty_jax.train --config experiments/synthetic.py``.

Any config field can be overridden, e.g. ``--config.model=dusty2``;
``--workdir`` holds checkpoints, metrics and pictures, and a run started
again in the same workdir resumes from its latest checkpoint.
"""

from absl import app, flags
from ml_collections import config_flags

from dusty_jax import parallel

FLAGS = flags.FLAGS
config_flags.DEFINE_config_file('config', 'experiments/synthetic.py',
                                'Experiment config file.', lock_config=True)
flags.DEFINE_string('workdir', 'runs/default', 'Where the run is written.')
flags.DEFINE_string('coordinator', None,
                    'host:port of process 0 for a multi-host run.')
flags.DEFINE_integer('num_processes', None, 'Processes in a multi-host run.')
flags.DEFINE_integer('process_id', None, 'This process in a multi-host run.')


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f'unexpected arguments: {argv[1:]}')
  parallel.initialize_distributed(FLAGS.coordinator, FLAGS.num_processes,
                                  FLAGS.process_id)
  from dusty_jax import configs, trainer  # after distributed init.
  try:
    trainer.train_and_evaluate(FLAGS.config, FLAGS.workdir)
  except (FileNotFoundError, configs.ConfigError, trainer.NonFiniteLossError) as e:
    raise SystemExit(f'error: {e}') from None


if __name__ == '__main__':
  app.run(main)
