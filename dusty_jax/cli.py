"""The command lines' one entry point: a user's mistake becomes one line.

``train`` and every tool call :func:`run`. The library raises; only here is
an error printed: one ``error: ...`` line on stderr and a non-zero exit
(2 for a bad flag or config, as absl does for bad flags; 1 otherwise), and
Ctrl-C is one line saying what a rerun does, exit 130. A bug in dusty_jax
still shows its traceback (and ``DUSTY_JAX_TRACEBACK=1`` shows one for any
error). While a command runs, orbax's log records and asyncio's reports are
silenced (checkpoint.quiet), which a library user's own program never is.
Not silenced: TensorStore's 'Event loop is closed' reports when an orbax
save or restore fails half-way (a disk filled by another writer during a
save, a checkpoint damaged without a size change or not in
checkpoints_sizes.json) may come before the one error line.
"""

from __future__ import annotations

import difflib
import errno
import importlib.util
import inspect
import logging
import os
import pickle
import sys

from absl import flags
from ml_collections import config_dict

from dusty_jax import errors

USAGE = 2        # a bad flag or config field, as absl exits for bad flags
FAILED = 1       # any other error a user's input caused
INTERRUPTED = 130  # 128 + SIGINT, as a shell reports Ctrl-C

# What a user's input can cause, besides dusty_jax's own types (errors.py,
# configs.ConfigError, checkpoint.CheckpointError): files named that are
# missing or unwritable, a full disk, a file that is not what it claims
# (UnpicklingError: authors.py's reader refuses it), a missing optional
# dependency, and the ValueError / KeyError with which the library's
# argument checks refuse a value.
_STANDARD = (OSError, ValueError, KeyError, ImportError, pickle.UnpicklingError)


class Exit(SystemExit):
  """Exits with ``status`` after :func:`fail` printed ``message``; str() is
  the message (tests match on it)."""

  def __init__(self, message: str, status: int):
    super().__init__(status)
    self.message = message

  def __str__(self):
    return self.message


def fail(message: str, status: int = FAILED):
  """Prints ``error: message`` (one line) on stderr and exits."""
  line = ' '.join(f'error: {message}'.split('\n'))
  print(line, file=sys.stderr, flush=True)
  raise Exit(line, status)


def _message(e: BaseException) -> str:
  if isinstance(e, KeyError) and e.args:
    return str(e.args[0])
  return str(e) or type(e).__name__


def run(fn, *args):
  """Calls ``fn(*args)``; a user's error exits with its one line."""
  # Imported here: orbax's import cost, for tools that never touch it.
  from dusty_jax import checkpoint
  # (and the configs' Flax: --help and a bad flag answer before it loads)
  from dusty_jax import configs
  own = (errors.UserError, checkpoint.CheckpointError)
  # JAX's import cost too: once a command runs, its programs compile once.
  from dusty_jax import xla_cache
  xla_cache.enable()
  try:
    with checkpoint.quiet():
      return fn(*args)
  except KeyboardInterrupt as e:
    if errors.show_traceback():
      raise
    print(str(e) if isinstance(e, errors.Interrupted) else 'interrupted',
          file=sys.stderr, flush=True)
    raise Exit('interrupted', INTERRUPTED) from None
  except own + _STANDARD as e:
    if errors.show_traceback():
      raise
    # The one line below says it all: writes orbax left running when the
    # disk filled would log their own copies when collected ("Task exception
    # was never retrieved"), maybe after this process printed its line.
    logging.getLogger('asyncio').setLevel(logging.CRITICAL)
    if isinstance(e, OSError) and e.errno == errno.ENOSPC:
      fail(f'no space left on device while writing {e.filename}; free space and '
           'rerun')
    fail(_message(e), USAGE if isinstance(e, configs.ConfigError) else FAILED)


# ----------------------------------------------------------------------------
# Flags: absl's and ml_collections' parse errors as one line.
# ----------------------------------------------------------------------------


def unknown_field(config, path: str) -> str | None:
  """The message for a config field ``path`` (``'data.dri'``) that
  ``config`` does not have, with the nearest known name, or that is a group
  of fields; None if it is a field of ``config``."""
  node, done = config, []
  for part in path.split('.'):
    if isinstance(node, (config_dict.ConfigDict, dict)) and part in node:
      node = node[part]
      done.append(part)
      continue
    if not isinstance(node, (config_dict.ConfigDict, dict)):
      return (f'unknown config field {path}: {".".join(done)} is a value, '
              'not a group of fields')
    close = difflib.get_close_matches(part, [str(k) for k in node.keys()], n=1)
    hint = f'; did you mean {".".join(done + close)}?' if close else ''
    return f'unknown config field {path}{hint}'
  if isinstance(node, config_dict.ConfigDict):
    presets = (' (the drops presets: --config experiments/study.py:MODEL,PRESET,SCALE)'
               if path == 'drops' else '')
    return (f'config field {path} is a group of fields ({", ".join(node.keys())}): '
            f'set them one by one, e.g. --config.{path}.{next(iter(node.keys()))}=...'
            f'{presets}')
  return None


def _fail_on_unknown_field(argv, values, config: str):
  """Exits with :func:`unknown_field`'s line for the first overridden field
  that the config file's config lacks or holds as a group, if any."""
  loaded = _load_config(_config_file(argv, values, config))
  for path in _config_paths(argv, config):
    msg = loaded is not None and unknown_field(loaded, path)
    if msg:
      fail(msg, USAGE)


def _config_paths(argv, name: str):
  """The fields overridden on the command line: ``--config.a.b=v``."""
  for arg in argv:
    prefix = f'--{name}.'
    if arg.startswith(prefix):
      yield arg[len(prefix):].split('=', 1)[0]


def parse_flags(argv, values: flags.FlagValues = flags.FLAGS,
                config: str | None = 'config'):
  """absl's ``flags_parser`` for app.run: parses ``argv`` into ``values``;
  an unknown flag, a bad value, a missing config file or an unknown config
  field (``config``: the name of the config file flag) is one line and exit
  2. Returns the arguments left."""
  if config is not None:
    argv = [_with_config_found(a, config) for a in argv]
    for i in range(1, len(argv)):
      if argv[i - 1] == f'--{config}':
        argv[i] = find_config(argv[i])
  try:
    rest = values(argv)
  except flags.Error as e:
    named = config and _config_file(argv, values, config)
    cause = named and 'Error whilst parsing config file' in str(e) and _load_config(
        named, errors=True)
    if isinstance(cause, Exception):
      # ml_collections' message holds the traceback; the error alone says it.
      fail(f'--{config}={named}: {_message(cause)}', USAGE)
    _fail_on_unknown_field(argv, values, config)
    fail(f'{e} (see --help)', USAGE)
  except (AttributeError, KeyError, TypeError, ValueError) as e:
    if config is None:
      raise
    # ml_collections' override of a config field that does not exist (or a
    # config file that does not load) is not a flags.Error.
    _fail_on_unknown_field(argv, values, config)
    fail(f'--{config}: {_message(e)}', USAGE)
  path = config and _config_file(argv, values, config)
  if path and not os.path.isfile(path.partition(':')[0]):
    fail(f'--{config}={path}: no such config file, here or in {EXPERIMENTS} '
         f'({", ".join(experiment_files())})', USAGE)
  return rest


# The repository's experiments/ (beside the package): a relative --config
# path not found in the working directory is looked up there, so that
# `--config experiments/synthetic.py` works from any directory.
EXPERIMENTS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                           'experiments')


def experiment_files() -> list[str]:
  """The config files of the repository's experiments/ (none when the
  package was installed without it)."""
  if not os.path.isdir(EXPERIMENTS):
    return []
  return sorted(f for f in os.listdir(EXPERIMENTS)
                if f.endswith('.py') and not f.startswith('_'))


def find_config(path: str) -> str:
  """``path`` (``FILE`` or ``FILE:ARG``) as given when FILE exists or is
  absolute, else the repository's experiments/ file of that name if there
  is one, else as given (the parse then says it is missing)."""
  file, sep, arg = path.partition(':')
  if not file or os.path.isabs(file) or os.path.isfile(file):
    return path
  found = os.path.join(EXPERIMENTS, os.path.basename(file))
  return found + sep + arg if os.path.isfile(found) else path


def _with_config_found(arg: str, name: str) -> str:
  prefix = f'--{name}='
  return prefix + find_config(arg[len(prefix):]) if arg.startswith(prefix) else arg


def _config_file(argv, values, name):
  """The config file named on the command line (the last, as absl takes),
  else the flag's default."""
  named = None
  for i, arg in enumerate(argv):
    if arg.startswith(f'--{name}='):
      named = arg.split('=', 1)[1]
    elif arg == f'--{name}' and i + 1 < len(argv):
      named = argv[i + 1]
  if named is not None:
    return named
  try:
    return values[name].default_unparsed if name in values else None
  except Exception:  # not a config file flag
    return None


def _load_config(path, errors: bool = False):
  """The config file's get_config(), as loaded before any override
  (ml_collections leaves the flag's value None when an override fails);
  if it does not load, None, or with ``errors`` the exception."""
  if not path:
    return None
  path, _, arg = path.partition(':')
  try:
    spec = importlib.util.spec_from_file_location('_dusty_jax_config', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    if arg and not inspect.signature(module.get_config).parameters:
      raise TypeError(f"this config takes no argument after ':' (got {arg!r}); "
                      'experiments/study.py does (its presets)')
    return module.get_config(arg) if arg else module.get_config()
  except Exception as e:  # the override error, already in hand, says enough then.
    return e if errors else None
