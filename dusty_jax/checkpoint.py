"""The one place that knows about orbax: save and restore train states, and
read one item (e.g. the EMA generator's variables) without the rest.

orbax's public API only (and nothing of ours but errors.py and files.py): a
failure is told by its type and the files on disk, never by a message's words.
A read or write failing half-way leaves TensorStore printing 'Event loop is
closed', so a step unlike its file sizes when saved (checkpoints_sizes.json,
beside checkpoints/) is not read, nor a save begun without room on the disk.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import gc
import json
import logging
import os
import shutil
import sys
import time

import jax
import orbax.checkpoint as ocp

from dusty_jax import errors, files

DIRECTORY, SIZES, DAMAGED = 'checkpoints', '_sizes.json', '_damaged'  # in a run; + siblings
ROOM_MARGIN = 1.2  # steps differ a little in how orbax packs arrays into files
UNREADABLE = Exception  # TensorStore's ValueErrors, OSErrors; a partial read: Exception
# For readers: the values orbax would otherwise set itself, with a warning each.
READ_ONLY = ocp.CheckpointManagerOptions(read_only=True, save_interval_steps=0, create=False)
_ORBAX = os.path.dirname(os.path.dirname(os.path.abspath(ocp.__file__)))
_stderr = functools.partial(print, file=sys.stderr)


class CheckpointError(errors.UserError, ValueError):
  """A checkpoint that cannot be read or written: which, and what a rerun does."""


class MissingItemError(KeyError):
  """A checkpoint holds no item of the asked name (not damage)."""


@contextlib.contextmanager
def quiet():
  """Drops orbax's log records (told by the file logging them) and asyncio's
  reports of the reads a failed restore abandons (a filter per call). The
  command lines hold it for a whole run: orbax saves in background threads."""
  drop = lambda r: r.name != 'asyncio' and not os.path.abspath(r.pathname).startswith(_ORBAX)
  loggers = [logging.getLogger(name) for name in ('absl', 'asyncio')]
  for logger in loggers:
    logger.addFilter(drop)
  try:
    yield
  except BaseException:
    gc.collect()  # the tasks a failure abandoned report when collected: now.
    raise
  finally:
    for logger in loggers:
      logger.removeFilter(drop)


def manager(workdir: str, keep: int = 3, keep_every: int = 0, cleanup_tmp: bool = False,
            log=None) -> ocp.CheckpointManager:
  """The run's checkpoints: the last ``keep`` steps and multiples of ``keep_every``.
  ``cleanup_tmp``: first remove (and ``log``) the folders of saves cut short, for a
  caller that holds the run directory alone (parallel.hold_workdir)."""
  path = os.path.join(os.path.abspath(workdir), DIRECTORY)
  if cleanup_tmp and jax.process_index() == 0 and os.path.isdir(path):
    cut = sorted(str(p.get()) for p in ocp.utils.tmp_checkpoints(path))
    for folder in cut:
      shutil.rmtree(folder)
    if cut and log:
      log(f"removed {len(cut)} unfinished checkpoint folder{'s' * (len(cut) > 1)} in {path} (a "
          f"save cut short by an earlier run's end): {', '.join(map(os.path.basename, cut))}")
  with quiet():  # it reads every step's metadata, warning about damaged ones.
    mngr = ocp.CheckpointManager(path, options=ocp.CheckpointManagerOptions(
        max_to_keep=keep, keep_period=keep_every or None, create=True))
  _note_sizes(path, unchecked=True)
  return mngr


def saved_steps(workdir: str) -> list[int]:
  """The steps of a run's finished checkpoints, oldest first."""
  path = os.path.join(os.path.abspath(workdir), DIRECTORY)
  return sorted(ocp.utils.checkpoint_steps(path)) if os.path.isdir(path) else []


def save(mngr: ocp.CheckpointManager, step: int, state, force: bool = False) -> bool:
  """Starts saving ``state`` as ``step`` in the background. The previous save's
  failure is a CheckpointError here, as is a disk without room for a step like
  the newest (one process: no peer waits). See errors.interrupts_deferred."""
  if not (force or mngr.should_save(step)):
    return False
  wait(mngr)
  directory = str(mngr.directory)
  with _write_errors(directory, step):
    if (jax.process_count() == 1 and
        shutil.disk_usage(directory).free < ROOM_MARGIN * _room(directory, state)):
      raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), directory)
    return mngr.save(step, args=ocp.args.StandardSave(state), force=force)


def wait(mngr: ocp.CheckpointManager):
  """Waits for the save in progress (a CheckpointError), notes the sizes saved."""
  directory = str(mngr.directory)
  saving = set(mngr.all_steps()) - set(ocp.utils.checkpoint_steps(directory))
  with _write_errors(directory, max(saving, default=None)):
    mngr.wait_until_finished()
  _note_sizes(directory)


@contextlib.contextmanager
def _write_errors(directory: str, step: int | None):
  try:
    with quiet():
      yield
  except Exception as e:  # of any type: the step did not save.
    intact = sorted(set(ocp.utils.checkpoint_steps(directory)) - {step})
    kept = (f"step{'s' * (len(intact) > 1)} {', '.join(map(str, intact))} "
            f"{'are' if len(intact) > 1 else 'is'} intact" if intact else
            'no checkpoint was saved before it')
    then = f'rerun to resume from {intact[-1]}' if intact else 'rerun to start afresh'
    what = 'a checkpoint' if step is None else f'checkpoint {step}'
    # TensorStore's full disk is a ValueError: it is told by the room left.
    full = any(isinstance(x, OSError) and x.errno == errno.ENOSPC for x in errors.causes(e))
    with contextlib.suppress(OSError):
      full = full or shutil.disk_usage(directory).free < _room(directory)
    raise CheckpointError(
        f'no space left on device while writing {what} in {directory}; {kept}; free space '
        f'and {then}' if full else f'writing {what} in {directory} failed '
        f'({errors.reason(e)}); {kept}; {then}') from e


def _room(directory: str, state=None) -> int:  # the newest step's, or state's
  steps = ocp.utils.checkpoint_steps(directory)
  return (sum(files.sizes(os.path.join(directory, str(max(steps))), blocks=True).values())
          if steps else sum(getattr(x, 'nbytes', 0) for x in jax.tree.leaves(state)))


def _read_sizes(directory: str) -> dict:
  with contextlib.suppress(OSError, ValueError, TypeError):  # none (an older run), or cut
    with open(os.path.normpath(directory) + SIZES) as f:
      return dict(json.load(f))
  return {}


def _note_sizes(directory: str, unchecked: bool = False):
  """Each step on disk with its files' sizes, noted when first seen (by process 0); with
  ``unchecked`` (a run opening) None: an earlier process may have died damaging it."""
  if jax.process_index() != 0:
    return
  old = _read_sizes(directory)
  new = {str(s): old[str(s)] if str(s) in old else None if unchecked else files.sizes(
      os.path.join(directory, str(s))) for s in ocp.utils.checkpoint_steps(directory)}
  if new != old:
    with contextlib.suppress(OSError), files.atomic_write(os.path.normpath(directory) + SIZES) as f:
      json.dump(new, f)


def restore_latest(mngr: ocp.CheckpointManager, target, log=_stderr,
                   set_aside: bool = False):
  """(state, step) of the newest checkpoint that restores, shaped and placed like
  ``target`` (each process reads what its devices hold), or (target, None). A
  damaged one is skipped with a line saying why; with ``set_aside`` (resuming) it
  moves to checkpoints_damaged/ beside, so that its step can be saved again."""
  directory = str(mngr.directory)
  abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, target)

  def move_aside(step):  # by process 0, for all
    src = os.path.join(directory, str(step))
    dst = os.path.join(directory + DAMAGED, f'{step}_{int(time.time())}')
    if jax.process_index() == 0 and os.path.isdir(src):
      os.makedirs(directory + DAMAGED, exist_ok=True)
      os.replace(src, dst)
      log(f'moved the damaged step {step} to {dst}')
    ocp.multihost.sync_global_processes(f'dusty_jax_moved_aside_{step}')
    with quiet():
      mngr.reload()

  if not mngr.all_steps():
    return target, None
  try:
    return _newest_that_restores(
        directory, mngr.all_steps(), log, lambda reader, step: reader.restore(
            step, args=ocp.args.StandardRestore(abstract)),
        on_damaged=move_aside if set_aside else None)
  except CheckpointError:
    if mngr.all_steps():
      raise
    log('no checkpoint restores (each was set aside); training starts afresh')
    return target, None


def restore_item(directory: str, name: str, step: int | None = None, log=_stderr):
  """(item ``name`` of a saved state in a run's checkpoints/ ``directory``, step), read
  alone as its metadata shapes it; without ``step``, of the newest that restores."""
  steps = sorted(ocp.utils.checkpoint_steps(directory)) if os.path.isdir(directory) else []
  if not steps or step not in steps + [None]:
    raise FileNotFoundError(f'{directory}: no checkpoint ' + (
        f'of step {step}; saved steps: {steps}' if steps else 'saved here'))

  def read(reader, s):
    tree = reader.item_metadata(s)
    tree = getattr(tree, 'tree', tree) or {}  # None where its metadata is gone
    if name not in tree:
      raise (MissingItemError(f'{directory}: step {s} holds no {name!r} (it holds '
                              f'{sorted(tree)})') if tree else ValueError('its metadata is gone'))
    device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    item = {name: jax.tree.map(lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype,
                                                              sharding=device), tree[name])}
    return reader.restore(s, args=ocp.args.PyTreeRestore(
        item, ocp.checkpoint_utils.construct_restore_args(item), partial_restore=True))[name]

  return _newest_that_restores(directory, steps if step is None else [step], log, read,
                               ocp.PyTreeCheckpointHandler(), fallback=step is None)


def _newest_that_restores(directory: str, steps, log, attempt, handlers=None,
                          on_damaged=None, fallback: bool = True):
  """(attempt(reader, step), step) for the newest of ``steps`` it succeeds on. A step
  that fails (damage seen, or an UNREADABLE error) is reported and, with ``fallback``,
  the one before tried (after ``on_damaged(step)``); without, a CheckpointError."""
  sizes = _read_sizes(directory)
  for i, step in enumerate(sorted(steps, reverse=True)):
    why = files.unlike(os.path.join(directory, str(step)), sizes.get(str(step)))
    try:
      if why is None:
        # A fresh reader per attempt: one whose restore failed fails the next.
        with quiet(), contextlib.closing(ocp.CheckpointManager(
            directory, options=READ_ONLY, item_handlers=handlers)) as reader:
          restored = attempt(reader, step)
        if i:
          log(f'loaded checkpoint step {step} from {directory}')
        return restored, step
    except MissingItemError:
      raise
    except UNREADABLE as e:
      why = f'unreadable: {errors.reason(e)}'
    if not fallback:
      raise CheckpointError(f'{directory}: checkpoint step {step} does not restore ({why})')
    log(f'warning: checkpoint step {step} in {directory} does not restore ({why}); '
        'trying the previous one')
    if on_damaged:
      on_damaged(step)
  raise CheckpointError(f'{directory}: no saved checkpoint restores (steps {sorted(steps)})')
