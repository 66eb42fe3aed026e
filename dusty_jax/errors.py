"""The errors a user's input can cause, apart from a bug in dusty_jax.

The library raises them; the command lines' one entry point (cli.py) prints
each as one ``error: ...`` line and exits non-zero, where a bug still shows
its traceback. configs.ConfigError and checkpoint.CheckpointError belong to
the family too (checkpoint.py imports nothing of ours, so it keeps its own).
"""

from __future__ import annotations


class UserError(Exception):
  """Something a user gave cannot work; the message says what and names it."""


class DataError(UserError, ValueError):
  """A dataset, prepared array or scan file that cannot be used."""


class Interrupted(KeyboardInterrupt):
  """Ctrl-C, with what a rerun does: where it stopped and what it resumes
  from. A KeyboardInterrupt, so code that catches that still does."""
