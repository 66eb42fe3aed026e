"""One process of the 2-process CPU test (run by test_train.py)."""

import os
import sys

os.environ['XLA_FLAGS'] = ('--xla_force_host_platform_device_count=1 '
                           '--xla_backend_optimization_level=0')  # as conftest
os.environ['JAX_PLATFORMS'] = 'cpu'

import jax  # noqa: E402

jax.config.update('jax_cpu_collectives_implementation', 'gloo')

import numpy as np  # noqa: E402


def main():
  port, pid, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
  # Generous timeouts: on a loaded 2-core machine one process may compile
  # for minutes while the other waits at a barrier.
  jax.distributed.initialize(f'127.0.0.1:{port}', num_processes=2,
                             process_id=pid, local_device_ids=[0],
                             initialization_timeout=900,
                             heartbeat_timeout_seconds=900,
                             shutdown_timeout_seconds=900)
  sys.path.insert(0, os.path.dirname(__file__))
  from train_helpers import run_steps
  params = run_steps(num_steps=2)
  if pid == 0:
    np.savez(out, *[np.asarray(x) for x in jax.tree.leaves(params)])
  jax.distributed.shutdown()


if __name__ == '__main__':
  main()
