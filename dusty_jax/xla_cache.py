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
its 3 s on a 2-core CPU). :func:`jit` keeps those too, for dusty_jax's own
functions: a function it wraps is traced once, exported (``jax.export``)
and written under ``$DUSTY_JAX_CACHE/export`` (under a JAX cache directory
the user named: its ``dusty_jax_export`` folder); a later process reads the
program back instead of tracing it. A file is keyed by what the trace
depends on: the function; the dusty_jax source; the versions of Python,
numpy, JAX, jaxlib, flax and optax; JAX's tracing settings; the platform;
the arguments' tree structure (with the static fields of a model's params),
avals and devices; the static arguments. Nothing is kept where the source
cannot stand for the code running (a file changed after the package
loaded; a module constant or function patched at run time; a model variant
or start a user registered). Anything that cannot be keyed, or fails to
read or run, is traced as jax.jit traces it.
"""

from __future__ import annotations

import ast
import enum
import functools
import hashlib
import importlib.metadata
import inspect
import os
import shutil
import sys
import tempfile
import time

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
OWN_EXPORT_FOLDER = 'dusty_jax_export'  # inside a JAX cache directory a user named
STALE_DAYS = 7  # folders of other sources unused this long are removed
STALE_TMP_S = 3600  # a write's .tmp file this old was cut short (a kill)
_PACKAGE = os.path.dirname(os.path.abspath(__file__))
_VERSIONED = ('numpy', 'jax', 'jaxlib', 'flax', 'optax', 'ml_dtypes')


def export_directory() -> str | None:
  """Where traced programs are kept, or None when the cache is off."""
  in_use = enable()
  if in_use is None or not jax.config.jax_enable_compilation_cache:
    return None
  if in_use == directory():
    return os.path.join(cache_root(), 'export')
  return os.path.join(in_use, OWN_EXPORT_FOLDER)


def source_digest() -> str | None:
  """SHA-1 of the dusty_jax package's Python source, or None where it cannot
  stand for the code running: a file changed after this process started
  (an edit, a reload), or no source to read."""
  loaded = sys.modules[__name__.split('.')[0]]._loaded_at
  h = hashlib.sha1()
  found = False
  try:
    for folder, dirs, files in os.walk(_PACKAGE):
      dirs[:] = sorted(d for d in dirs if not d.startswith(('.', '__')))
      for name in sorted(f for f in files if f.endswith('.py')):
        path = os.path.join(folder, name)
        with open(path, 'rb') as f:
          stat = os.fstat(f.fileno())
          if max(stat.st_mtime, stat.st_ctime) >= loaded:  # ctime: a copy keeping mtimes
            return None
          h.update(os.path.relpath(path, _PACKAGE).encode() + b'\0' + f.read())
        found = True
  except OSError:  # a file gone mid-update, say
    return None
  return h.hexdigest() if found else None


@functools.lru_cache(maxsize=None)
def _environment() -> str:
  """The versions the traced code depends on, as text."""
  versions = [sys.version.split()[0]]
  for name in _VERSIONED:
    try:
      versions.append(f'{name} {importlib.metadata.version(name)}')
    except importlib.metadata.PackageNotFoundError:
      versions.append(f'{name} -')
  return ', '.join(versions)


def _trace_context():
  """JAX's settings that change what tracing makes (what jax.jit keys its
  own cache on), or None where JAX does not expose them."""
  try:
    from jax._src import config as jax_config  # private: guarded
    return jax_config.trace_context()
  except Exception:
    return None


_PLAIN = (str, int, float, bool, type(None), enum.Enum)


def _trace_settings() -> str | None:
  """_trace_context as text, or None where it holds more than plain values
  (a mesh in use, say), which text would not tell apart."""
  context = _trace_context()
  if context is None:
    return None
  text = []
  for value in context:
    if isinstance(value, tuple) and not _is_plain(value):
      return None
    text.append(value if _is_plain(value) else type(value).__name__)
  return repr(text)


@functools.lru_cache(maxsize=None)
def _defaults(path: str) -> tuple[dict, tuple]:
  """What a module's source sets at its top level: (plain literal values by
  name, function names)."""
  with open(path, encoding='utf-8') as f:
    body = ast.parse(f.read()).body
  values, functions = {}, []
  for node in body:
    target = (node.targets[0] if isinstance(node, ast.Assign) and len(node.targets) == 1
              else node.target if isinstance(node, ast.AnnAssign) and node.value else None)
    if isinstance(target, ast.Name):
      try:
        value = ast.literal_eval(node.value)
      except (ValueError, SyntaxError, TypeError):
        continue
      if _is_plain(value):
        values[target.id] = value
    elif isinstance(node, ast.FunctionDef):
      functions.append(node.name)
  return values, tuple(functions)


def _is_plain(value) -> bool:
  if isinstance(value, tuple):
    return all(_is_plain(v) for v in value)
  return isinstance(value, _PLAIN)


def patched() -> bool:
  """Whether a loaded dusty_jax module's constant or function differs from
  what its source sets (a user's or a test's patch, which the source digest
  cannot see): then nothing is kept."""
  package = __name__.split('.')[0]
  for name, module in list(sys.modules.items()):
    path = getattr(module, '__file__', None)
    if name.split('.')[0] != package or not path or not path.endswith('.py'):
      continue
    try:
      values, functions = _defaults(path)
    except (OSError, SyntaxError, ValueError):
      return True
    now = vars(module)
    for attr, value in values.items():
      if attr in now and not (type(now[attr]) is type(value) and now[attr] == value):
        return True
    for attr in functions:
      fn = now.get(attr)
      if (getattr(fn, '__module__', None) != name
          or getattr(fn, '__qualname__', None) != attr):
        return True
  return False


def _devices(leaves) -> set:
  return {d for x in leaves for d in x.sharding.device_set}


def _device(leaves):
  """The device the arguments are on (the default one where none is)."""
  devices = _devices(leaves)
  return devices.pop() if devices else jax.devices()[0]


@functools.lru_cache(maxsize=None)
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


def _weak(x) -> bool:
  return getattr(x, 'weak_type', False)  # typed keys have none


def _is_key(x) -> bool:
  return jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


class _Exported:
  """A function jitted as jax.jit does, whose traced program is kept on disk
  (see the module docstring). ``exportable(**arguments)`` says whether a
  call may use a kept program."""

  def __init__(self, fun, static_argnames, exportable):
    self.fun = fun
    self.jitted = jax.jit(fun, static_argnames=static_argnames)
    self.static_argnames = tuple(static_argnames)
    self.exportable = exportable
    self.signature = inspect.signature(fun)
    self.name = f'{fun.__module__}.{fun.__qualname__}'
    self.own = fun.__module__.split('.')[0] == __name__.split('.')[0]
    self.names = {}     # (tree, avals, static) -> file path, or None: not kept
    self.programs = {}  # file path -> jitted call of the kept program
    functools.update_wrapper(self, fun)

  def _cache_size(self) -> int:
    """Programs traced in this process (jax.jit's count, and the kept ones)."""
    return self.jitted._cache_size() + len(self.programs)

  def __call__(self, *args, **kwargs):
    folder = None if not self.own or jax.config.jax_disable_jit else export_directory()
    if folder is None:
      return self.jitted(*args, **kwargs)
    bound = self.signature.bind(*args, **kwargs)
    bound.apply_defaults()
    static = {k: bound.arguments[k] for k in self.static_argnames}
    leaves, tree = jax.tree.flatten([v for k, v in bound.arguments.items()
                                     if k not in static])
    if any(isinstance(x, jax.core.Tracer) for x in leaves) or (
        self.exportable and not self.exportable(**bound.arguments)):
      return self.jitted(*args, **kwargs)  # inside traced code it inlines
    # Python and numpy values as jax.jit sees them (weak types, canonical dtypes).
    leaves = [x if isinstance(x, jax.Array) else jnp.asarray(x) for x in leaves]
    memo = (tree, tuple((x.shape, x.dtype, _weak(x), x.sharding) for x in leaves),
            tuple(static.items()), _trace_context(), folder)
    if memo not in self.names:
      self.names[memo] = self._path(folder, leaves, tree, static)
    path = self.names[memo]
    if path is None:
      return self.jitted(*args, **kwargs)
    flat = [jax.random.key_data(x) if _is_key(x) else x for x in leaves]
    if path in self.programs:
      return self.programs[path](*flat)
    program, read = self._program(path, flat, leaves, tree, static)
    if program is not None:
      try:
        out = program(*flat)
        self.programs[path] = program
        return out
      except Exception:  # damaged, or not for this jaxlib: jax.jit's instead
        if read:
          _remove(path)  # the next process traces it anew
    self.names[memo] = None  # not kept in this process: jax.jit from now on
    return self.jitted(*args, **kwargs)

  def _path(self, folder, leaves, tree, static) -> str | None:
    """The kept program's file under ``folder`` for these arguments, or None
    where the call cannot be keyed."""
    digest, settings = source_digest(), _trace_settings()
    if (not _can_serialise() or digest is None or settings is None or '://' in folder
        or len(_devices(leaves)) > 1 or patched()):
      return None
    device = _device(leaves)
    avals = [(tuple(x.shape), str(x.dtype), _weak(x),
              str(jax.random.key_impl(x)) if _is_key(x) else '') for x in leaves]
    text = repr((self.name, _environment(), settings, device.platform,
                 device.device_kind, jax.default_backend(), str(tree), avals,
                 sorted((k, _static_repr(v)) for k, v in static.items())))
    if ' at 0x' in text:  # a repr that names an address differs per process
      return None
    key = hashlib.sha1(text.encode()).hexdigest()[:20]
    return os.path.join(folder, digest[:16], f'{self.name}-{key}{EXPORT_SUFFIX}')

  def _program(self, path, flat, leaves, tree, static):
    """(jitted call of the program kept at ``path``, whether it was read):
    read, or traced, exported and written; (None, False) where it cannot be
    exported."""
    from jax import export  # only where a program is kept
    try:
      with open(path, 'rb') as f:
        program = jax.jit(export.deserialize(bytearray(f.read())).call)
      os.utime(os.path.dirname(path))  # in use: not pruned
      return program, True
    except Exception:  # absent, or unreadable (torn, another format)
      pass
    key_impls = [jax.random.key_impl(x) if _is_key(x) else None for x in leaves]

    def flat_fun(*flat_args):
      args = [a if i is None else jax.random.wrap_key_data(a, impl=i)
              for a, i in zip(flat_args, key_impls)]
      return self.fun(*jax.tree.unflatten(tree, args), **static)

    try:
      exported = export.export(jax.jit(flat_fun), platforms=(_device(leaves).platform,))(
          *flat)
      data = exported.serialize()
    except Exception:  # not exportable (a user's error surfaces from jax.jit)
      return None, False
    _write(path, data)
    return jax.jit(exported.call), False


def _remove(path: str):
  try:
    os.remove(path)
  except OSError:
    pass


def _write(path: str, data: bytes):
  """Writes ``data`` to ``path`` atomically, and removes the .tmp files of
  writes cut short. A new source's first program also removes the folders of
  other sources unused for STALE_DAYS."""
  folder = os.path.dirname(path)
  tmp = None
  try:
    if not os.path.isdir(folder):
      os.makedirs(folder, exist_ok=True)
      _prune(os.path.dirname(folder), keep=os.path.basename(folder))
    fd, tmp = tempfile.mkstemp(dir=folder, suffix='.tmp')
    with os.fdopen(fd, 'wb') as f:
      f.write(data)
    os.replace(tmp, path)
    tmp = None
    limit = time.time() - STALE_TMP_S
    for entry in os.scandir(folder):
      if entry.name.endswith('.tmp') and entry.stat().st_mtime < limit:
        _remove(entry.path)
  except OSError:  # a read-only or full cache: the program is still used
    pass
  finally:
    if tmp is not None:
      _remove(tmp)


def _prune(root: str, keep: str):
  """Removes the source folders under ``root`` other than ``keep`` that
  nothing was written to for STALE_DAYS."""
  limit = time.time() - STALE_DAYS * 86400
  for name in os.listdir(root):
    folder = os.path.join(root, name)
    if name != keep and os.path.isdir(folder) and os.path.getmtime(folder) < limit:
      shutil.rmtree(folder, ignore_errors=True)


def jit(fun=None, *, static_argnames=(), exportable=None):
  """``jax.jit(fun, static_argnames=...)`` whose traced program a later
  process reads from disk instead of tracing it again (module docstring);
  for functions of dusty_jax only (the source of others is not keyed: they
  are jitted as jax.jit does). ``exportable(**arguments)``: whether a call
  may be kept (e.g. only with the default loss function). Inside other
  traced code, and under jax.disable_jit, it is jax.jit."""
  if fun is None:
    return functools.partial(jit, static_argnames=static_argnames, exportable=exportable)
  return _Exported(fun, static_argnames, exportable)
