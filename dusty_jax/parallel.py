"""The one place that knows about devices, meshes and hosts.

Data parallelism in the pmap programming model, built with ``jax.shard_map``
over a 1-D mesh named ``'data'`` (what ``jax.pmap`` itself compiles to since
JAX 0.8): the state is replicated, the batch is split along its first axis,
and the per-device step ``pmean``-s its gradients over ``'data'``. Several
hosts join with :func:`initialize_distributed`; the mesh then spans every
device of every process, and each process feeds its own slice of the batch.
"""

from __future__ import annotations

import os

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from dusty_jax import configs

AXIS = 'data'


def initialize_distributed(coordinator: str | None = None,
                           num_processes: int | None = None,
                           process_id: int | None = None):
  """Joins a multi-host run when asked (flags or JAX_COORDINATOR_ADDRESS).

  A no-op for a single process.
  """
  coordinator = coordinator or os.environ.get('JAX_COORDINATOR_ADDRESS')
  if not coordinator:
    return
  jax.distributed.initialize(coordinator_address=coordinator,
                             num_processes=num_processes,
                             process_id=process_id)


# Measured on a 2-core CPU by benchmarks/research/speed/xla_flags.py
# (cpu_devices_study.json in its results/): the study step is fastest with 4
# devices (shards of 4), slower with 8 (shards of 2).
MIN_CPU_SHARD = 4      # examples per CPU device, at least
CPU_DEVICES_PER_CORE = 2


def cpu_device_count(batch_size: int, cores: int | None = None) -> int:
  """CPU devices for a one-process run of ``batch_size``: the most, up to
  CPU_DEVICES_PER_CORE per core, that divide the batch into shards of at
  least MIN_CPU_SHARD examples (1 when none do)."""
  if not cores:  # the cores this process may run on, where the OS says.
    cores = (len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity')
             else os.cpu_count() or 1)
  return max([n for n in range(1, CPU_DEVICES_PER_CORE * cores + 1)
              if batch_size % n == 0 and batch_size // n >= MIN_CPU_SHARD] or [1])


def use_cpu_cores(batch_size: int, processes: int = 1) -> int | None:
  """Gives XLA's CPU backend several devices for data parallelism.

  On one CPU device the small study step gains little from a second core
  (x1.26, against x1.62 for the authors' PyTorch step); several devices,
  each with its shard of the batch, run side by side and keep the cores
  busy (x1.5 on 2 cores; benchmarks/research/speed/README.md). cpu_device_count says
  how many. Randomness is drawn per example, so the run draws the same
  numbers on any number of devices.

  Must run before JAX's first operation. Returns the count set, or None
  where it leaves the count alone: when the user chose one
  (``JAX_NUM_CPU_DEVICES`` or XLA's ``--xla_force_host_platform_device_count``),
  the backends are already up with another, or the run spans several
  processes (CPU collectives across hosts with several devices each are not
  measured). On a GPU machine only the unused CPU backend changes.
  """
  chosen = ('JAX_NUM_CPU_DEVICES' in os.environ or
            'xla_force_host_platform_device_count' in os.environ.get('XLA_FLAGS', ''))
  if chosen or processes > 1:
    return None
  n = cpu_device_count(batch_size)
  try:
    jax.config.update('jax_num_cpu_devices', n)
  except RuntimeError:  # backends already initialised: leave them as they are.
    return None
  return n


def data_mesh(devices=None) -> Mesh:
  return Mesh(np.asarray(devices if devices is not None else jax.devices()),
              (AXIS,))


def data_parallel(per_device_step, mesh: Mesh, donate: bool = True):
  """jit(shard_map(step)) for ``step(state, batch, key) -> (state, metrics)``."""
  sharded = jax.shard_map(per_device_step, mesh=mesh,
                          in_specs=(P(), P(AXIS), P()),
                          out_specs=(P(), P()))
  return jax.jit(sharded, donate_argnums=(0,) if donate else ())


def replicate(tree, mesh: Mesh):
  return jax.device_put(tree, NamedSharding(mesh, P()))


def shard_batch(local_batch: np.ndarray, mesh: Mesh):
  """A global batch array from this process's slice (split over 'data')."""
  return jax.make_array_from_process_local_data(
      NamedSharding(mesh, P(AXIS)), np.asarray(local_batch))


def local_batch_size(global_batch: int, mesh: Mesh) -> int:
  n_dev, n_proc = mesh.size, jax.process_count()
  if global_batch % n_dev:
    raise configs.ConfigError(f'config field batch_size={global_batch}: is not divisible '
                              f'by the {n_dev} devices of the data mesh; use a '
                              f'multiple of {n_dev}')
  return global_batch // n_proc


def to_host(tree):
  """Fetches replicated arrays to numpy (one copy, not a device axis)."""
  return jax.tree.map(lambda x: np.asarray(jax.device_get(x)), tree)
