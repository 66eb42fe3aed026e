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

The persistent cache skips XLA's compilation, not the tracing and lowering
before it, which is most of a second process's first ``invert`` (about 2 of
its 3 s on a 2-core CPU). :func:`jit` keeps those too: a function it wraps
is traced once, exported (``jax.export``) and written under
``$DUSTY_JAX_CACHE/export``; a later process reads the program back instead
of tracing it. A file is keyed by everything the trace depends on: the
function, the dusty_jax source, the JAX version and platform, the arguments'
tree structure (with the static fields of a model's params) and avals, and
the static arguments; anything that cannot be keyed, or fails to read, is
traced as jax.jit traces it.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import os
import tempfile

import jax
import jax.numpy as jnp

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


# --- Traced programs kept on disk (jax.export) -------------------------------
EXPORT_SUFFIX = '.jaxexport'


def export_directory() -> str | None:
  """Where exported programs go, or None when the cache is off."""
  if enable() is None:
    return None
  return os.path.join(cache_root(), 'export')


@functools.lru_cache(maxsize=None)
def _source_digest() -> str:
  """SHA-1 of the dusty_jax package's Python source: a changed line makes
  every exported program stale."""
  root = os.path.dirname(os.path.abspath(__file__))
  h = hashlib.sha1()
  for folder, dirs, files in os.walk(root):
    dirs[:] = sorted(d for d in dirs if not d.startswith(('.', '__')))
    for name in sorted(f for f in files if f.endswith('.py')):
      path = os.path.join(folder, name)
      h.update(os.path.relpath(path, root).encode())
      with open(path, 'rb') as f:
        h.update(f.read())
  return h.hexdigest()


def _can_serialise() -> bool:
  try:
    import flatbuffers  # noqa: F401  (jax.export's serialisation needs it)
    return True
  except ImportError:
    return False


def _static_repr(value) -> str:
  """A static argument as text: a module-level function by its name (its
  repr names an address); anything else by its repr."""
  name = getattr(value, '__qualname__', None)
  if inspect.isfunction(value) and '<' not in name:
    return f'{value.__module__}.{name}'
  return repr(value)


def _is_key(x) -> bool:
  return jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


class _Exported:
  """A function jitted as jax.jit does, whose traced program is kept on disk
  (see the module docstring). ``exportable(**static)`` says whether a call
  with those static arguments may use the kept program."""

  def __init__(self, fun, static_argnames, exportable):
    self.fun = fun
    self.jitted = jax.jit(fun, static_argnames=static_argnames)
    self.static_argnames = tuple(static_argnames)
    self.exportable = exportable
    self.signature = inspect.signature(fun)
    self.name = f'{fun.__module__}.{fun.__qualname__}'
    self.programs = {}  # file name -> jitted call of the exported program
    functools.update_wrapper(self, fun)

  def _cache_size(self) -> int:
    """Programs traced in this process (jax.jit's count, and the kept ones)."""
    return self.jitted._cache_size() + len(self.programs)

  def __call__(self, *args, **kwargs):
    bound = self.signature.bind(*args, **kwargs)
    bound.apply_defaults()
    static = {k: bound.arguments[k] for k in self.static_argnames}
    dynamic = [v for k, v in bound.arguments.items() if k not in static]
    leaves, tree = jax.tree.flatten(dynamic)
    if export_directory() is None or any(isinstance(x, jax.core.Tracer) for x in leaves):
      return self.jitted(*args, **kwargs)  # inside traced code: inline, as jax.jit
    # Python and numpy values as jax.jit sees them (weak types, canonical dtypes).
    leaves = [x if isinstance(x, jax.Array) else jnp.asarray(x) for x in leaves]
    name = self._file_name(leaves, tree, static)
    if name is None:
      return self.jitted(*args, **kwargs)
    flat = [jax.random.key_data(x) if _is_key(x) else x for x in leaves]
    program = self.programs.get(name) or self._program(name, flat, leaves, tree, static)
    if program is None:
      return self.jitted(*args, **kwargs)
    return program(*flat)

  def _file_name(self, leaves, tree, static) -> str | None:
    """The kept program's file name for these arguments, or None where the
    call cannot use one (cache off, traced arguments, an unkeyable part)."""
    if not _can_serialise() or (self.exportable and not self.exportable(**static)):
      return None
    avals = []
    for x in leaves:
      if len(x.sharding.device_set) > 1:
        return None
      key_impl = str(jax.random.key_impl(x)) if _is_key(x) else ''
      avals.append((tuple(x.shape), str(x.dtype), getattr(x, 'weak_type', False), key_impl))
    device = jax.devices()[0]
    text = repr((self.name, jax.__version__, device.platform, device.device_kind,
                 bool(jax.config.jax_enable_x64), jax.config.jax_default_matmul_precision,
                 str(tree), avals,
                 sorted((k, _static_repr(v)) for k, v in static.items())))
    if ' at 0x' in text:  # a repr that names an address differs per process
      return None
    digest = hashlib.sha1(text.encode()).hexdigest()[:20]
    return f'{self.name}-{_source_digest()[:12]}-{digest}{EXPORT_SUFFIX}'

  def _program(self, name, flat, leaves, tree, static):
    """The jitted call of the program kept in ``name``: read, or traced,
    exported and written; None where neither works."""
    from jax import export  # jax.export: only where a program is kept
    folder = export_directory()
    path = os.path.join(folder, name)
    exported = None
    try:
      with open(path, 'rb') as f:
        exported = export.deserialize(bytearray(f.read()))
    except Exception:  # absent, or unreadable (torn, another JAX): trace anew
      exported = None
    if exported is None:
      key_impls = [jax.random.key_impl(x) if _is_key(x) else None for x in leaves]

      def flat_fun(*flat_args):
        args = [jax.random.wrap_key_data(a, impl=i) if i is not None else a
                for a, i in zip(flat_args, key_impls)]
        return self.fun(*jax.tree.unflatten(tree, args), **static)

      try:
        exported = export.export(jax.jit(flat_fun))(*flat)
        _write(folder, name, exported.serialize(), prefix=f'{self.name}-')
      except Exception:  # what cannot be exported is traced as jax.jit does
        return None
    program = jax.jit(exported.call)
    self.programs[name] = program
    return program


def _write(folder: str, name: str, data: bytes, prefix: str):
  """Writes ``data`` to folder/name atomically, and removes the files of
  ``prefix`` that an older dusty_jax source wrote."""
  try:
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, suffix='.tmp')
    with os.fdopen(fd, 'wb') as f:
      f.write(data)
    os.replace(tmp, os.path.join(folder, name))
    current = f'{prefix}{_source_digest()[:12]}-'
    for other in os.listdir(folder):
      if other.startswith(prefix) and not other.startswith(current):
        os.remove(os.path.join(folder, other))
  except OSError:  # a read-only or full cache: the program is still used
    pass


def jit(fun=None, *, static_argnames=(), exportable=None):
  """``jax.jit(fun, static_argnames=...)`` whose traced program a later
  process reads from disk instead of tracing it again (module docstring).
  ``exportable(**static)``: whether calls with these static arguments may
  be kept (e.g. only with the default loss function). Inside other traced
  code it inlines, as jax.jit does."""
  if fun is None:
    return functools.partial(jit, static_argnames=static_argnames, exportable=exportable)
  return _Exported(fun, static_argnames, exportable)
