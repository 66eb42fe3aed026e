"""What runs after the last training step: named steps that
config.after_training lists (as big_vision's config names its evaluators),
run in order by trainer.train_and_evaluate. Each takes the finished run and
returns it, its generator changed where the step changes it.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax

from dusty_jax import evaluation, generator, levels


@dataclasses.dataclass(frozen=True)
class Trained:
  """A finished training, as the steps after it see it."""
  config: Any
  workdir: str
  step: int  # the last step trained
  generator: generator.GeneratorParams  # the EMA generator, on the host
  data_dir: str  # the prepared dataset
  depth: Any  # its training split (N, H, W), metric depth
  log: Any


def fit_drop_levels(run: Trained) -> Trained:
  """'levels': where ``drops.depth_levels`` is set, the EMA generator's drop
  levels per (ring, depth) cell fitted to inversions of training scans
  (evaluation.fit_levels) and written to the run (levels.FILE, which loading
  the run applies). A finished run started again reads the ones it wrote."""
  if not run.config.drops.depth_levels:
    return run
  path = os.path.join(run.workdir, levels.FILE)
  kept = levels.load(run.workdir)
  if kept is not None and kept[1] == run.step:
    return dataclasses.replace(run, generator=levels.with_levels(run.generator, kept[0], path))
  # Every process fits the same levels (same inversions); one writes.
  is_main = jax.process_index() == 0
  if is_main:
    run.log(f'fitting drop levels per (ring, depth) cell to inversions of '
            f'{min(len(run.depth), evaluation.LEVEL_SCANS)} training scans')
  fitted = evaluation.fit_levels(run.generator, run.depth, progress=is_main)
  if is_main:
    levels.save(run.workdir, fitted.variables['params']['depth_levels'], run.step)
    run.log(f'drop levels written: {levels.FILE} (applied when step {run.step} is loaded)')
  return dataclasses.replace(run, generator=fitted)


def final_evaluation(run: Trained) -> Trained:
  """'final_evaluation': where ``final_eval`` has scans, a short evaluation
  on the test split (evaluation.after_training), once per run."""
  fe = run.config.final_eval
  if not (fe.num_synthesis or fe.num_invert) or os.path.isfile(
      os.path.join(run.workdir, evaluation.AFTER_TRAINING + '.json')):
    return run
  if jax.process_count() > 1:  # the others would wait for process 0 at JAX's exit
    if jax.process_index() == 0:
      run.log(f'final_eval is left to one process: python -m dusty_jax.tools.evaluate '
              f'--workdir {run.workdir}')
    return run
  run.log('short evaluation on the test split (config final_eval)')
  run.log(evaluation.summary(evaluation.after_training(
      run.generator, run.data_dir, run.workdir, num_synthesis=fe.num_synthesis,
      points=fe.points, num_invert=fe.num_invert, invert_steps=fe.invert_steps)))
  return run


# config.after_training's names (configs.AFTER_TRAINING) and their steps.
STEPS = {'levels': fit_drop_levels, 'final_evaluation': final_evaluation}
