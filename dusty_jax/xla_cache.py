"""JAX's persistent compilation cache, under the dusty_jax cache directory.

Compiling the inversion's search or a sampler takes tens of seconds on a
CPU, each time a process starts. The command lines (cli.run) and the
library's heavy entry points (invert, sample, generate, encoder.encode,
load_pretrained) call :func:`enable`, so a second process making the same
call loads the compiled program from ``$DUSTY_JAX_CACHE/xla`` (default
``~/.cache/dusty_jax/xla``) instead of compiling it again.

``DUSTY_JAX_COMPILATION_CACHE=0`` (or ``off``, ``false``, ``no``) leaves
JAX's cache alone. A cache directory the user configured for JAX
(``JAX_COMPILATION_CACHE_DIR`` or ``jax.config.update``) is kept, and so is
a minimum compile time they set; JAX's own ``jax_enable_compilation_cache``
still turns every cache off.
"""

from __future__ import annotations

import os

import jax

ENV = 'DUSTY_JAX_COMPILATION_CACHE'
OFF = ('0', 'off', 'false', 'no')
# Programs compiling in less than this are not written (JAX's default is 1 s).
# The inversion's search and the samplers take seconds to minutes; the
# encoder's start under a second on a quiet 2-core CPU.
MIN_COMPILE_SECS = 0.2
_JAX_DEFAULT_MIN_SECS = 1.0

_state = {'done': False, 'directory': None}


def cache_root() -> str:
  """The dusty_jax cache directory: ``$DUSTY_JAX_CACHE`` or
  ``~/.cache/dusty_jax`` (the rule of data.pipeline.default_cache, which
  data/ keeps for itself: the model side does not import the pipeline)."""
  return os.environ.get('DUSTY_JAX_CACHE',
                        os.path.join(os.path.expanduser('~'), '.cache', 'dusty_jax'))


def directory() -> str:
  """Where dusty_jax keeps compiled programs when the user named none."""
  return os.path.join(cache_root(), 'xla')


def enable() -> str | None:
  """Turns the persistent compilation cache on (once per process); returns
  the directory in use, or None when it is off. Cheap after the first call."""
  if _state['done']:
    return _state['directory']
  _state['done'] = True
  if os.environ.get(ENV, '').strip().lower() in OFF:
    return None
  own = jax.config.jax_compilation_cache_dir
  if own:  # the user's own cache: theirs to configure.
    _state['directory'] = own
    return own
  path = directory()
  try:
    os.makedirs(path, exist_ok=True)
  except OSError:  # a read-only home: compile as JAX does without a cache.
    return None
  jax.config.update('jax_compilation_cache_dir', path)
  if ('JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS' not in os.environ and
      jax.config.jax_persistent_cache_min_compile_time_secs == _JAX_DEFAULT_MIN_SECS):
    jax.config.update('jax_persistent_cache_min_compile_time_secs', MIN_COMPILE_SECS)
  _state['directory'] = path
  return path
