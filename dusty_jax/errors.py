"""The errors a user's input can cause, apart from a bug in dusty_jax.

The library raises them; the command lines' one entry point (cli.py) prints
each as one ``error: ...`` line and exits non-zero, where a bug still shows
its traceback. configs.ConfigError and checkpoint.CheckpointError belong to
the family too (defined beside what raises them).
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading

import numpy as np

TRACEBACK_ENV = 'DUSTY_JAX_TRACEBACK'


class UserError(Exception):
  """Something a user gave cannot work; the message says what and names it."""


class DataError(UserError, ValueError):
  """A dataset, prepared array or scan file that cannot be used."""


class Interrupted(KeyboardInterrupt):
  """Ctrl-C, with what a rerun does: where it stopped and what it resumes
  from. A KeyboardInterrupt, so code that catches that still does."""


@contextlib.contextmanager
def interrupts_deferred():
  """A Ctrl-C that comes inside is raised on the way out. For a trainer's
  loop around checkpoint.save: orbax's save cut half-way leaves writes that
  print tracebacks as the program ends. Swaps the SIGINT handler while
  inside, on the main thread (no other gets SIGINT)."""
  if threading.current_thread() is not threading.main_thread():
    yield
    return
  caught = []
  previous = signal.signal(signal.SIGINT, lambda *a: caught.append(a))
  try:
    yield
  finally:
    signal.signal(signal.SIGINT, previous)
    if caught and previous is signal.default_int_handler:
      raise KeyboardInterrupt
    if caught and callable(previous):
      previous(*caught[0])


class InputError(UserError, ValueError):
  """An array or number passed to a library call that cannot give a right
  answer: NaN or inf where a finite value is needed, a count beyond int32,
  a value outside its usable range, half precision where it loses range."""


INT32_MAX = 2 ** 31 - 1  # counts are int32 inside the compiled programs
HALF = ('float16', 'bfloat16')  # too coarse for normalised inverse depth (codec.py)


def widen_half(tree):
  """``tree`` with its float16 and bfloat16 arrays cast to float32, the
  precision dusty_jax computes in (the half-precision policy: weights and
  latents widen, normalised inverse depth is refused, codec.check_precision).
  The same object when it holds none."""
  import jax  # here: errors.py is imported by tools that need no JAX first
  half = lambda v: hasattr(v, 'dtype') and np.dtype(v.dtype).name in HALF
  if not any(half(v) for v in jax.tree.leaves(tree)):
    return tree
  return jax.tree.map(lambda v: v.astype(np.float32) if half(v) else v, tree)


def is_concrete(x) -> bool:
  """True unless ``x`` is a tracer: checks read values only outside jit."""
  import jax  # here: errors.py is imported by tools that need no JAX first
  return not isinstance(x, jax.core.Tracer)


def check_finite(x, what: str, hint: str = 'give finite numbers'):
  """``x`` unchanged; InputError naming ``what``, how many and the first bad
  value, if a concrete ``x`` holds NaN or inf, or a value beyond float32's
  range (dusty_jax computes in float32). A tracer passes unread."""
  if not is_concrete(x):
    return x
  a = np.asarray(x)
  if a.dtype.kind == 'f' or a.dtype.name in HALF:
    with np.errstate(over='ignore'):  # beyond float32 is what is looked for
      bad = ~np.isfinite(a.astype(np.float32))
    if bad.any():
      first = tuple(int(i) for i in np.argwhere(bad)[0]) if a.ndim else ()
      raise InputError(f'{what}: {int(bad.sum())} of {a.size} values are NaN, inf or '
                       f'beyond float32 (the first, {float(a[first])!r}, at index '
                       f'{first}); {hint}')
  return x


def check_count(n, what: str, low: int = 0, high: int = INT32_MAX) -> int:
  """``n`` as an int; InputError naming ``what`` unless it is a whole number
  in [low, high] (high: int32's largest, as counts are int32 when compiled)."""
  if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not low <= n <= high:
    limit = ' and <= 2**31 - 1 (int32, as compiled)' if high == INT32_MAX else f' and <= {high}'
    raise InputError(f'{what}={n!r}: must be a whole number >= {low}{limit}')
  return int(n)


def causes(e: BaseException) -> list:
  """``e`` and the exceptions it was raised from or during, in order."""
  seen = []
  while e is not None and e not in seen:
    seen.append(e)
    e = e.__cause__ or e.__context__
  return seen


def reason(e: BaseException) -> str:
  """'TYPE: the first line of its message' (200 characters at most)."""
  text = str(e).strip()
  return f'{type(e).__name__}: {text.splitlines()[0][:200]}' if text else type(e).__name__


def show_traceback() -> bool:
  """Whether the user asked for tracebacks (``DUSTY_JAX_TRACEBACK=1``; empty,
  ``0``, ``false``, ``no`` or ``off`` do not): every error then ends in its
  traceback instead of one line, and a process ended for a lost peer dumps
  the stacks of its threads."""
  return os.environ.get(TRACEBACK_ENV, '').strip().lower() not in ('', '0', 'false', 'no',
                                                                  'off')
