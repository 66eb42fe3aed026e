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
