"""The one place that knows about orbax: save and restore train states, and
read one item (e.g. the EMA generator's variables) without the rest.

Imports nothing of dusty_jax: what a run directory means is generator.py's
and trainer.py's business.
"""

from __future__ import annotations

import contextlib
import errno
import gc
import json
import logging
import os
import re
import shutil
import signal
import sys
import threading
import time

import jax
import orbax.checkpoint as ocp

DIRECTORY = 'checkpoints'  # inside a run directory
# For readers: the values orbax would otherwise set itself, with a warning each.
READ_ONLY = ocp.CheckpointManagerOptions(read_only=True, save_interval_steps=0,
                                         create=False)


class CheckpointError(ValueError):
  """A checkpoint that cannot be read or written; the message says which and
  what a rerun does. (One of the errors the command lines print as one line;
  defined here because this module imports nothing of dusty_jax.)"""


def _stderr(message: str):
  print(message, file=sys.stderr)


# ----------------------------------------------------------------------------
# orbax's and TensorStore's chatter, silenced only around dusty_jax's own use
# of them (see :func:`quiet`), never for the rest of a program.
# ----------------------------------------------------------------------------

_ORBAX_DIR = os.path.dirname(os.path.dirname(os.path.abspath(ocp.__file__)))


class _DropOrbaxRecords(logging.Filter):
  """orbax logs through absl: per load 'Given directory is read only', per
  save dozens of info lines, and its failures once more as ERROR records
  with tracebacks, which reach us as exceptions anyway."""

  def filter(self, record):
    return not os.path.abspath(record.pathname).startswith(_ORBAX_DIR)


class _DropAsyncioReports(logging.Filter):
  """asyncio's 'Task exception was never retrieved' about the reads a failed
  restore abandons (each with a TensorStore spec dump)."""

  def filter(self, record):
    return False


_quiet_lock = threading.Lock()
_quiet_depth = 0
_FILTERS = {'absl': _DropOrbaxRecords(), 'asyncio': _DropAsyncioReports()}


@contextlib.contextmanager
def quiet():
  """Inside: orbax's absl log records and asyncio's reports about the reads
  and writes a failed restore or save abandons are dropped (filters on those
  two loggers); everything else (the caller's own logs, other libraries) is
  untouched, and the filters go on leaving. Re-entrant; the command lines
  hold it for a whole run, since orbax saves in background threads.

  Not silenced: when a restore or save fails half-way, orbax closes its
  event loop while TensorStore reads or writes still run, and each may print
  'RuntimeError: Event loop is closed' from its own thread (the interpreter's
  hook for unraisable errors, which a library leaves alone). So orbax is not
  started on what is known to fail: a step whose files differ in size from
  its manifest, a save the disk has no room for. A disk filled by another
  writer during a save, or a step damaged without a size change or without a
  manifest, can still print these reports before the error."""
  global _quiet_depth
  with _quiet_lock:
    _quiet_depth += 1
    if _quiet_depth == 1:
      for name, f in _FILTERS.items():
        logging.getLogger(name).addFilter(f)
  try:
    yield
  finally:
    with _quiet_lock:
      _quiet_depth -= 1
      if _quiet_depth == 0:
        gc.collect()  # abandoned tasks report now, while quiet.
        for name, f in _FILTERS.items():
          logging.getLogger(name).removeFilter(f)


# The folder of a save in progress: STEP.orbax-checkpoint-tmp[-TIMESTAMP].
_TMP = re.compile(r'\d+' + re.escape('.orbax-checkpoint-tmp') + r'(-\d+)?')


def manager(workdir: str, keep: int = 3, interval: int = 1,
            keep_every: int = 0, cleanup_tmp: bool = False,
            log=None) -> ocp.CheckpointManager:
  """The run's checkpoint manager: the last ``keep`` steps, and with
  ``keep_every`` also every step that is a multiple of it.

  ``cleanup_tmp``: remove the tmp directories of saves cut short (a kill, a
  crash, a lost peer), which would block saving those steps again, before
  the manager starts (orbax's own clean-up runs in the background and may
  not finish), and ``log`` which. Only for a caller that holds the run
  directory alone (the trainer, parallel.hold_workdir): another's save in
  progress would be deleted."""
  path = os.path.join(os.path.abspath(workdir), DIRECTORY)
  if cleanup_tmp and jax.process_index() == 0 and os.path.isdir(path):
    cut = sorted(n for n in os.listdir(path) if _TMP.fullmatch(n))
    for name in cut:
      shutil.rmtree(os.path.join(path, name))
    if cut and log:
      log(f"removed {len(cut)} unfinished checkpoint folder{'s' * (len(cut) > 1)} "
          f"in {path} (a save cut short by an earlier run's end): {', '.join(cut)}")
  opts = ocp.CheckpointManagerOptions(max_to_keep=keep, keep_period=keep_every or None,
                                      save_interval_steps=interval, create=True,
                                      cleanup_tmp_directories=cleanup_tmp)
  with quiet():  # it reads every step's metadata, warning about damaged ones.
    return ocp.CheckpointManager(path, options=opts)


def saved_steps(workdir: str) -> list[int]:
  """The steps of a run's finished checkpoints, oldest first (a save in
  progress is not among them); reads the directory only."""
  path = os.path.join(os.path.abspath(workdir), DIRECTORY)
  return sorted(ocp.utils.checkpoint_steps(path)) if os.path.isdir(path) else []


def save(mngr: ocp.CheckpointManager, step: int, state, force: bool = False) -> bool:
  """Starts saving ``state`` as ``step`` (in the background). A failure of
  the previous save surfaces here, as a CheckpointError saying which steps
  are intact; so does a disk without room for one more step, found before
  orbax starts writing (checked only in a single-process run, where no peer
  can be left waiting for a save that one process refused)."""
  with quiet(), _write_errors(mngr, step), _interrupt_after():
    if not (force or mngr.should_save(step)):
      return False
    mngr.wait_until_finished()  # as orbax's save does first
    _list_finished(mngr)
    if jax.process_count() == 1:
      _check_room(str(mngr.directory), state)
    started = mngr.save(step, args=ocp.args.StandardSave(state), force=force)
    if started:
      _unlisted.setdefault(str(mngr.directory), set()).add(step)
    return started


@contextlib.contextmanager
def _interrupt_after():
  """Takes a Ctrl-C that arrives while orbax starts a save once the save is
  started: interrupted half-way, orbax leaves a background commit that
  nothing waits for, which fails noisily as the interpreter exits."""
  if threading.current_thread() is not threading.main_thread():
    yield
    return
  caught = []
  previous = signal.signal(signal.SIGINT, lambda *a: caught.append(a))
  try:
    yield
  finally:
    signal.signal(signal.SIGINT, previous)
    if caught:
      if previous is signal.default_int_handler:
        raise KeyboardInterrupt
      if callable(previous):
        previous(*caught[0])


def wait(mngr: ocp.CheckpointManager):
  """Waits for the save in progress; its failure is a CheckpointError."""
  with quiet(), _write_errors(mngr, None):
    mngr.wait_until_finished()
    _list_finished(mngr)


# What a save needs beyond the newest step's size on disk (steps differ a
# little in how orbax packs their arrays into files).
ROOM_MARGIN = 1.2
MANIFEST = 'dusty_files.json'  # in a step's folder: {file: size} when saved
_unlisted = {}  # {checkpoint directory: steps this process started saving}


def _check_room(directory: str, state):
  """Raises ENOSPC unless the disk has room for one more step like the
  newest saved one (with none, for ``state``'s arrays), with a margin: a
  save that runs out of room half-way leaves TensorStore writes running on
  an event loop orbax has closed, each printing a traceback."""
  steps = ocp.utils.checkpoint_steps(directory)
  if steps:
    newest = os.path.join(directory, str(max(steps)))
    need = sum(os.stat(os.path.join(d, f)).st_blocks * 512
               for d, _, fs in os.walk(newest) for f in fs)
  else:
    need = sum(getattr(x, 'nbytes', 0) for x in jax.tree.leaves(state))
  if shutil.disk_usage(directory).free < need * ROOM_MARGIN:
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _sizes(step_dir: str) -> dict:
  """{path relative to ``step_dir``: size in bytes} of its files but ours."""
  paths = [os.path.join(d, f) for d, _, fs in os.walk(step_dir) for f in fs
           if not f.startswith(MANIFEST)]
  return {os.path.relpath(p, step_dir): os.path.getsize(p) for p in paths}


def _list_finished(mngr):
  """Writes the manifest of each step this process started saving in
  ``mngr``'s directory that has committed since (on process 0, for all):
  a restore then checks the files' sizes before orbax reads them."""
  directory = str(mngr.directory)
  steps = _unlisted.pop(directory, set())
  if jax.process_index() != 0:
    return
  for step in steps & set(ocp.utils.checkpoint_steps(directory)):
    path = os.path.join(directory, str(step), MANIFEST)
    try:
      with open(path + '.tmp', 'w') as f:
        json.dump(_sizes(os.path.dirname(path)), f)
      os.replace(path + '.tmp', path)
    except OSError:  # no manifest: orbax reads the step unchecked, as before.
      with contextlib.suppress(OSError):
        os.remove(path + '.tmp')


def _no_space(e: BaseException) -> bool:
  for x in causes(e):
    if (isinstance(x, OSError) and x.errno == errno.ENOSPC) or re.search(
        r'RESOURCE_EXHAUSTED|No space left on device|os_error_code=.?28', str(x)):
      return True
  return False


def causes(e: BaseException) -> list:
  """``e`` and the exceptions it was raised from or during, in order."""
  seen = []
  while e is not None and e not in seen:
    seen.append(e)
    e = e.__cause__ or e.__context__
  return seen


@contextlib.contextmanager
def _write_errors(mngr, step):
  try:
    yield
  except Exception as e:  # orbax and TensorStore raise many types.
    directory = str(mngr.directory)
    text = ' '.join(str(x) for x in causes(e))
    failed = re.search(re.escape(directory.rstrip('/')) + r'/(\d+)\.orbax-checkpoint-tmp',
                       text)
    failed = int(failed.group(1)) if failed else step
    intact = sorted(s for s in ocp.utils.checkpoint_steps(directory) if s != failed)
    if intact:
      kept = (f'step {intact[0]} is intact' if len(intact) == 1 else
              f"steps {', '.join(map(str, intact[:-1]))} and {intact[-1]} are intact")
      then = f'rerun to resume from {intact[-1]}'
    else:
      kept, then = 'no checkpoint was saved before it', 'rerun to start afresh'
    what = f'checkpoint {failed}' if failed is not None else 'a checkpoint'
    if _no_space(e):
      raise CheckpointError(f'no space left on device while writing {what} in '
                            f'{directory}; {kept}; free space and {then}') from None
    raise CheckpointError(f'writing {what} in {directory} failed ({_reason(e)}); '
                          f'{kept}; {then}') from e


def restore(mngr: ocp.CheckpointManager, step: int, target):
  """The state saved at ``step``, shaped and placed like ``target``: each
  process reads the part that its own devices hold."""
  abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, target)
  return mngr.restore(step, args=ocp.args.StandardRestore(abstract))


def restore_latest(mngr: ocp.CheckpointManager, target, log=_stderr,
                   set_aside: bool = False):
  """(state, step) from the newest checkpoint that restores, or (target, None).

  A damaged checkpoint (truncated file, missing metadata, empty step
  directory) is skipped with a message saying which step and why, and the
  previous one is tried. With ``set_aside`` (when training resumes) the
  damaged step directory is moved to ``checkpoints_damaged/`` beside it, so
  that the step can be saved again; nothing is deleted.
  """
  with quiet():  # orbax warns about the metadata of damaged steps.
    steps = mngr.all_steps()
  if not steps:
    return target, None

  def move_aside(step):
    if jax.process_index() != 0:  # the primary process moves it for all,
      ocp.multihost.sync_global_processes(f'dusty_jax_moved_aside_{step}')  # then they reload.
      with quiet():
        mngr.reload()
      return
    src = os.path.join(str(mngr.directory), str(step))
    dst = os.path.join(os.path.dirname(str(mngr.directory).rstrip('/')),
                       'checkpoints_damaged', f'{step}_{int(time.time())}')
    if os.path.isdir(src):
      os.makedirs(os.path.dirname(dst), exist_ok=True)
      os.replace(src, dst)
      log(f'moved the damaged step {step} to {dst}')
    if jax.process_count() > 1:
      ocp.multihost.sync_global_processes(f'dusty_jax_moved_aside_{step}')
    with quiet():
      mngr.reload()

  try:
    return _newest_that_restores(
        mngr.directory, steps, lambda reader, step: restore(reader, step, target),
        log, on_damaged=move_aside if set_aside else None)
  except CheckpointError:
    with quiet():
      left = mngr.all_steps()
    if left:
      raise
    log('no checkpoint restores (each was set aside); training starts afresh')
    return target, None


class MissingItemError(KeyError):
  """A checkpoint holds no item of the asked name (not damage)."""


def restore_item(directory: str, name: str, step: int | None = None, log=_stderr):
  """(item ``name`` of a saved state, step): reads only that item.

  ``directory``: a run's checkpoints/. Without ``step``, the newest step that
  restores (damaged ones are skipped with a message). Shapes come from the
  checkpoint's own metadata, so no model needs to be built; nothing is
  written.
  """
  if not os.path.isdir(directory):
    raise FileNotFoundError(f'{directory}: no checkpoints here')
  steps = sorted(ocp.utils.checkpoint_steps(directory))
  if not steps:
    raise FileNotFoundError(f'{directory}: no checkpoint saved yet')
  if step is not None and step not in steps:
    raise FileNotFoundError(f'{directory}: no checkpoint of step {step}; saved '
                            f'steps: {steps}')

  def read(reader, s):
    meta = reader.item_metadata(s)
    tree = getattr(meta, 'tree', meta)
    if isinstance(tree, dict) and tree and name not in tree:
      raise MissingItemError(f'{directory}: step {s} holds no {name!r} (it holds '
                             f'{sorted(tree)})')
    device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    target = {name: jax.tree.map(lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype),
                                 tree[name])}
    args = jax.tree.map(lambda m: ocp.ArrayRestoreArgs(dtype=m.dtype, sharding=device),
                        target)
    return reader.restore(s, args=ocp.args.PyTreeRestore(
        item=target, restore_args=args, partial_restore=True))[name]

  return _newest_that_restores(directory, steps if step is None else [step], read, log,
                               handlers=ocp.PyTreeCheckpointHandler(),
                               fallback=step is None)


def _reason(e: Exception) -> str:
  text = str(e).strip()
  return f'{type(e).__name__}: {text.splitlines()[0][:200]}' if text else type(e).__name__


def _damage(step_dir: str, e: Exception) -> str:
  """Why a step does not restore, in words a person can act on."""
  files = [os.path.join(d, f) for d, _, fs in os.walk(step_dir) for f in fs]
  if not os.path.isdir(step_dir) or not files:
    return 'empty step directory'
  names = {os.path.basename(f) for f in files}
  if '_CHECKPOINT_METADATA' not in names or '_METADATA' not in names:
    return 'metadata missing'
  text = ' '.join(str(x) for x in causes(e))
  if re.search(r'OUT_OF_RANGE|truncat|reading array index|Error reading', text):
    return 'data file truncated'
  if re.search(r'DATA_LOSS|checksum|corrupt', text, re.I):
    return 'data file damaged'
  return f'unreadable: {_reason(e)}'


def _unlike_saved(step_dir: str) -> str | None:
  """Why a step's files differ from its manifest, or None when they match
  or it has none (a step saved before manifests, or cut off before its
  manifest was written)."""
  try:
    with open(os.path.join(step_dir, MANIFEST)) as f:
      saved = json.load(f)
  except (OSError, ValueError):
    return None
  now = _sizes(step_dir)
  if not now:
    return 'empty step directory'
  bad = sorted(n for n in saved if now.get(n) != saved[n])
  if not bad:
    return None
  if any(os.path.basename(n) in ('_CHECKPOINT_METADATA', '_METADATA') for n in bad
         if n not in now):
    return 'metadata missing'
  name, more = bad[0], f', and {len(bad) - 1} more files' if len(bad) > 1 else ''
  if name not in now:
    return f'data file missing: {name}{more}'
  what = 'truncated' if now[name] < saved[name] else 'damaged'
  return f'data file {what}: {name} has {now[name]} bytes, {saved[name]} when saved{more}'


def _newest_that_restores(directory, steps, attempt, log, handlers=None,
                          on_damaged=None, fallback: bool = True):
  """(attempt(reader, step), step) for the newest of ``steps`` it succeeds on.

  A step that fails is reported and, with ``fallback``, the previous one is
  tried (``on_damaged(step)`` first); without, the failure is a ValueError.
  A step whose files differ from its manifest fails without orbax reading
  it. A MissingItemError is the caller's mistake, not damage: it propagates.
  """
  skipped = False
  for step in sorted(steps, reverse=True):
    step_dir = os.path.join(str(directory), str(step))
    why = _unlike_saved(step_dir)  # orbax is not asked to read a damaged step
    if why is None:
      with quiet():
        # A fresh reader per attempt: a failed restore leaves a manager's item
        # handlers in a state where the next restore fails too.
        reader = ocp.CheckpointManager(directory, options=READ_ONLY,
                                       item_handlers=handlers)
        try:
          restored = attempt(reader, step)
        except MissingItemError:
          raise
        except Exception as e:  # orbax/TensorStore raise many types.
          why = _damage(step_dir, e)
        finally:
          reader.close()
    if why is not None:
      if not fallback:
        raise CheckpointError(f'{directory}: checkpoint step {step} does not '
                              f'restore ({why})') from None
      log(f'warning: checkpoint step {step} in {directory} does not restore '
          f'({why}); trying the previous one')
      skipped = True
      if on_damaged:
        on_damaged(step)
      continue
    if skipped:
      log(f'loaded checkpoint step {step} from {directory}')
    return restored, step
  raise CheckpointError(f'{directory}: no saved checkpoint restores (steps '
                        f'{sorted(steps)})')
