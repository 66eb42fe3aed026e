"""The one place that knows about orbax: save and restore train states, and
read one item (e.g. the EMA generator's variables) without the rest.

Imports nothing of dusty_jax: what a run directory means is generator.py's
and trainer.py's business.
"""

from __future__ import annotations

import os
import time

import jax
import orbax.checkpoint as ocp

DIRECTORY = 'checkpoints'  # inside a run directory
# For readers: the values orbax would otherwise set itself, with a warning each.
READ_ONLY = ocp.CheckpointManagerOptions(read_only=True, save_interval_steps=0,
                                         create=False)


def manager(workdir: str, keep: int = 3, interval: int = 1) -> ocp.CheckpointManager:
  path = os.path.join(os.path.abspath(workdir), DIRECTORY)
  opts = ocp.CheckpointManagerOptions(max_to_keep=keep,
                                      save_interval_steps=interval, create=True)
  return ocp.CheckpointManager(path, options=opts)


def save(mngr: ocp.CheckpointManager, step: int, state, force: bool = False) -> bool:
  return mngr.save(step, args=ocp.args.StandardSave(state), force=force)


def restore(mngr: ocp.CheckpointManager, step: int, target):
  """The state saved at ``step``, shaped like ``target``."""
  abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, target)
  return mngr.restore(step, args=ocp.args.StandardRestore(abstract))


def restore_latest(mngr: ocp.CheckpointManager, target, log=print,
                   set_aside: bool = False):
  """(state, step) from the newest checkpoint that restores, or (target, None).

  A damaged checkpoint (truncated file, missing metadata, empty step
  directory) is skipped with a message saying which step and why, and the
  previous one is tried. With ``set_aside`` (when training resumes) the
  damaged step directory is moved to ``checkpoints_damaged/`` beside it, so
  that the step can be saved again; nothing is deleted.
  """
  if not mngr.all_steps():
    return target, None

  def move_aside(step):
    src = os.path.join(str(mngr.directory), str(step))
    dst = os.path.join(os.path.dirname(str(mngr.directory).rstrip('/')),
                       'checkpoints_damaged', f'{step}_{int(time.time())}')
    if os.path.isdir(src):
      os.makedirs(os.path.dirname(dst), exist_ok=True)
      os.replace(src, dst)
      log(f'moved the damaged step {step} to {dst}')
    mngr.reload()

  try:
    return _newest_that_restores(
        mngr.directory, mngr.all_steps(), lambda reader, step: restore(reader, step, target),
        log, on_damaged=move_aside if set_aside else None)
  except FileNotFoundError:
    if mngr.all_steps():
      raise
    return target, None  # every step was damaged and set aside: start afresh


class MissingItemError(KeyError):
  """A checkpoint holds no item of the asked name (not damage)."""


def restore_item(directory: str, name: str, step: int | None = None, log=print):
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


def _newest_that_restores(directory, steps, attempt, log, handlers=None,
                          on_damaged=None, fallback: bool = True):
  """(attempt(reader, step), step) for the newest of ``steps`` it succeeds on.

  A step that fails is reported and, with ``fallback``, the previous one is
  tried (``on_damaged(step)`` first); without, the failure is a ValueError.
  A MissingItemError is the caller's mistake, not damage: it propagates.
  """
  for step in sorted(steps, reverse=True):
    # A fresh reader per attempt: a failed restore leaves a manager's item
    # handlers in a state where the next restore fails too.
    reader = ocp.CheckpointManager(directory, options=READ_ONLY, item_handlers=handlers)
    try:
      return attempt(reader, step), step
    except MissingItemError:
      raise
    except Exception as e:  # orbax/TensorStore raise many types.
      if not fallback:
        raise ValueError(f'{directory}: checkpoint step {step} does not restore '
                         f'({_reason(e)})') from None
      log(f'warning: checkpoint step {step} in {directory} does not restore '
          f'({_reason(e)}); trying the previous one')
      if on_damaged:
        on_damaged(step)
    finally:
      reader.close()
  raise FileNotFoundError(f'{directory}: no saved checkpoint restores (steps '
                          f'{sorted(steps)})')
