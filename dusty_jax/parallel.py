"""The one place that knows about devices, meshes and hosts.

Data parallelism in the pmap programming model, built with ``jax.shard_map``
over a 1-D mesh named ``'data'`` (what ``jax.pmap`` itself compiles to since
JAX 0.8): the state is replicated, the batch is split along its first axis,
and the per-device step ``pmean``-s its gradients over ``'data'``. Several
hosts join with :func:`initialize_distributed`; the mesh then spans every
device of every process, and each process feeds its own slice of the batch.

The processes of a run also keep watch on each other (:class:`PeerWatch`),
and agree on what each holds (:func:`hold_workdir`).
"""

from __future__ import annotations

import contextlib
import errno
import faulthandler
import fcntl
import itertools
import os
import re
import socket
import sys
import threading
import time

import jax
import numpy as np
from jax._src import distributed as jax_distributed
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from dusty_jax import configs, errors

AXIS = 'data'

# Seconds without a sign of life from another process of the run after which
# a process gives up (train.py's --peer_timeout).
PEER_TIMEOUT_S = 60
_run = {'coordinator': None}  # the coordination service's address, once joined


def initialize_distributed(coordinator: str | None = None,
                           num_processes: int | None = None,
                           process_id: int | None = None,
                           peer_timeout: float = PEER_TIMEOUT_S):
  """Joins a multi-host run when asked (flags or JAX_COORDINATOR_ADDRESS).

  A no-op for a single process. JAX's own heartbeat, which ends a process
  with a C++ abort when a peer stops, is set well beyond ``peer_timeout``,
  so that :class:`PeerWatch` speaks first.
  """
  coordinator = coordinator or os.environ.get('JAX_COORDINATOR_ADDRESS')
  if not coordinator:
    return
  _run['coordinator'] = coordinator
  jax.distributed.initialize(coordinator_address=coordinator,
                             num_processes=num_processes,
                             process_id=process_id,
                             heartbeat_timeout_seconds=int(max(100, 2 * peer_timeout + 30)))


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
  """``tree`` on every device of ``mesh``. Across processes each process
  places its own copy on its own devices (a device_put onto devices of
  another process is a cross-host transfer, which JAX's CPU backend lacks);
  every process must pass the same values."""
  sharding = NamedSharding(mesh, P())
  if jax.process_count() == 1:
    return jax.device_put(tree, sharding)

  def put(x):
    if isinstance(x, jax.Array):
      if x.sharding.is_equivalent_to(sharding, x.ndim):
        return x
      x = x.addressable_data(0)  # this process's copy
    return jax.make_array_from_process_local_data(sharding, np.asarray(x))
  return jax.tree.map(put, tree)


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


# ----------------------------------------------------------------------------
# The processes of a run: a watch on each other, and agreement.
# ----------------------------------------------------------------------------

LOST_EXIT = 1  # as cli.FAILED
_keys = itertools.count()  # each process makes the same calls in the same order


def _client():
  # JAX's coordination-service client: private, read as orbax's own
  # multihost.get_jax_distributed_client does.
  return jax_distributed.global_state.client


def joined() -> bool:
  """Whether this process joined a multi-process run (starts no backend)."""
  return _client() is not None


def _namespace(name: str) -> str:
  return f'dusty_jax/{name}/{next(_keys)}'


def all_texts(name: str, text: str, timeout: float = 3600.0) -> list[str]:
  """Every process's ``text``, in process order (all must call it). The
  keys it sets in the coordination service are deleted again once every
  process has read them (a training calls it at each log step)."""
  if jax.process_count() == 1:
    return [text]
  client, key = _client(), _namespace(name)
  mine, ms = f'{key}/{jax.process_index()}', int(timeout * 1000)
  client.key_value_set(mine, 'v' + text)
  texts = [client.blocking_key_value_get(f'{key}/{p}', ms)[1:]
           for p in range(jax.process_count())]
  client.wait_at_barrier(f'{key}/read', ms)
  client.key_value_delete(mine)
  return texts


def fail_now(message: str):
  """Prints ``error: message`` and ends this process at once: a process
  whose peer is lost cannot finish (JAX's exit handler would wait for the
  peer at its shutdown barrier, then abort with a C++ stack trace). With
  DUSTY_JAX_TRACEBACK=1 the stacks of all threads follow the line."""
  # On a line of its own: a progress bar may hold the current one.
  print(f'\nerror: {message}', file=sys.stderr, flush=True)
  if errors.show_traceback():
    faulthandler.dump_traceback(all_threads=True)
  sys.stdout.flush()
  os._exit(LOST_EXIT)  # pylint: disable=protected-access


# What Gloo's TCP transport says when the process at the other end is gone.
_GLOO_LOST = re.compile(r'gloo/transport/\S+\] (Read|Write) error .*(Connection reset by peer|'
                        r'Broken pipe|Connection refused)')


def is_peer_loss(e: BaseException) -> bool:
  """Whether an error of a multi-process run is a lost peer: a runtime error
  of a collective (Gloo, NCCL) or of the coordination service that lost a
  process; the coordination service's address (process 0) refusing or
  unavailable; or any error that carries Gloo's word for a lost connection
  (a checkpoint's write reports one in its own words). Another address that
  is unavailable or refuses (a storage service, a download) is not a peer."""
  if jax.process_count() < 2:
    return False
  text = str(e)
  if _GLOO_LOST.search(text):
    return True
  if not isinstance(e, jax.errors.JaxRuntimeError):
    return False
  if any(w in text for w in ('Gloo', 'NCCL', 'heartbeat', 'coordination service')):
    return True
  port = (_run['coordinator'] or '').rpartition(':')[2]
  refused = re.search(r'UNAVAILABLE|Connection refused|Connection reset', text)
  return bool(port and refused and re.search(rf':{re.escape(port)}(?!\d)', text))


class PeerWatch:
  """Ends this process, in one line, when another process of the run stops.

  Each process beats (a counter it raises every ``timeout / 10`` s) in JAX's
  coordination service; a peer whose beat stops for ``timeout`` seconds, or
  a coordination service (process 0) that stops answering for as long, is
  lost: ``fail_now(describe(reason))``. Beats come from a thread of their
  own, so a long compilation or a blocked collective does not stop them. A
  process that ends its work calls :meth:`finish` (its peers stop watching
  it); :meth:`close` alone stops watching. A no-op for one process.
  """

  def __init__(self, timeout: float, describe):
    self.timeout, self.describe = float(timeout), describe
    self.n, self.me = jax.process_count(), jax.process_index()
    self._stop = threading.Event()
    if self.n == 1:
      return
    self._client, self._key = _client(), _namespace('beat')
    now = time.monotonic()
    self._seen = {p: (None, now) for p in range(self.n) if p != self.me}
    self._answered = now  # the last time the coordination service answered
    self._period = max(self.timeout / 10, 0.1)
    for target in (self._beat, self._judge):
      threading.Thread(target=target, daemon=True, name=f'dusty_jax{target.__name__}').start()

  def _beat(self):
    beat = 0
    while not self._stop.wait(self._period):
      try:
        self._client.key_value_set(f'{self._key}/{self.me}', str(beat), allow_overwrite=True)
        beat += 1
        for p, (value, _) in list(self._seen.items()):
          try:
            now_value = self._client.key_value_try_get(f'{self._key}/{p}')
          except jax.errors.JaxRuntimeError as e:
            if 'NOT_FOUND' in str(e):
              continue  # no beat yet
            raise
          if now_value == 'done':
            del self._seen[p]
          elif now_value != value:
            self._seen[p] = (now_value, time.monotonic())
        self._answered = time.monotonic()
      except Exception:  # the service is gone: _judge tells when it is lost.
        pass

  def _judge(self):
    while not self._stop.wait(self._period):
      now = time.monotonic()
      if now - self._answered > self.timeout:
        self.lost(f'the coordination service (process 0) gave no answer for '
                  f'{self.timeout:g} s')
      for p, (_, since) in list(self._seen.items()):
        if now - since > self.timeout:
          self.lost(f'process {p} gave no sign of life for {self.timeout:g} s')

  def lost(self, reason: str):
    """Ends this process: a peer is lost for ``reason``."""
    self._stop.set()
    fail_now(self.describe(reason))

  def finish(self):
    """This process's work is done: peers stop watching it; stops the watch."""
    if self.n > 1 and not self._stop.is_set():
      self._stop.set()
      with contextlib.suppress(Exception):
        self._client.key_value_set(f'{self._key}/{self.me}', 'done', allow_overwrite=True)

  def close(self):
    self._stop.set()


# One training per run directory: a lock file per process of the run (so a
# run's own processes do not refuse each other, and another run's do).
LOCK_FILE = 'train.lock'


class WorkdirInUse(errors.UserError):
  """Another training holds the run directory."""


@contextlib.contextmanager
def hold_workdir(workdir: str):
  """Holds ``workdir`` for this training: an OS lock (flock) on
  ``train.lock`` in it (``train.lock.K`` for process K of a multi-process
  run), naming its holder's pid and host. The OS drops the lock when the
  process ends, kill -9 included, so nothing is left to clean by hand. If
  any process of the run finds its lock held, every process refuses, in
  one line naming the holder, before anything is written. On leaving,
  process K > 0 removes its ``train.lock.K`` (``train.lock``, which process
  0 holds throughout, keeps the directory for the run meanwhile), and a
  directory it made, left holding nothing but lock files (a training that
  failed before writing), is removed again."""
  if os.path.exists(workdir) and not os.path.isdir(workdir):
    raise errors.UserError(f'{workdir}: a file, not a directory; give a run directory '
                           '(a new one, or a run to resume)')
  made = not os.path.isdir(workdir)
  os.makedirs(workdir, exist_ok=True)
  k = jax.process_index()
  path = os.path.join(workdir, LOCK_FILE + (f'.{k}' if k else ''))
  fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
  held = False
  try:
    refused = ''
    try:
      fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
      held = True
    except OSError as e:
      if e.errno not in (errno.EWOULDBLOCK, errno.EACCES):
        raise
      holder = os.pread(fd, 256, 0).decode(errors='replace').strip()
      refused = f'{path} is held by {holder or "a training just starting"}'
    refusals = [r for r in all_texts('lock', refused) if r]
    if refusals:
      raise WorkdirInUse(f'{workdir} is in use by another training ({"; ".join(refusals)}); '
                         'wait for it to end, or use another --workdir')
    os.ftruncate(fd, 0)
    os.pwrite(fd, f'pid {os.getpid()} on host {socket.gethostname()}\n'.encode(), 0)
    yield
  finally:
    # Only a lock this process holds goes. The train.lock that every run's
    # process 0 takes still guards the directory after a train.lock.K goes.
    if held and (k or (made and all(f.startswith(LOCK_FILE) for f in os.listdir(workdir)))):
      with contextlib.suppress(OSError):
        os.unlink(path)
        if made:
          os.rmdir(workdir)  # fails while another process's lock file is there
    os.close(fd)  # releases the lock
