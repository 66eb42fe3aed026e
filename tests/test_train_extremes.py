"""Training at the extremes of its settings: a few steps of the smoke
config's networks on tiny scans, each run finite and moving.

The settings at the ends of what configs.validate accepts, and two data
extremes: lr 10x and 0.1x the default, one example per device, R1 gamma 0
and 100 (every step), tau at both ends of gumbel.TAU_RANGE, scans 95%
dropped and scans with no drop. Each compiles a step of its own (they are
static), so they go in three runs: the harsh ends together (large steps,
strong R1, the spiky low-tau gradient, sparse data), the mild ends
together (small steps, no R1, the flat high-tau gradient, full scans), and
one example on each of 4 devices. Contract: every metric of every step
finite, the generator, discriminator and EMA weights finite, and the
losses and weights moved.
"""

import jax
import numpy as np
import pytest

from dusty_jax import configs, gumbel
from train_helpers import run_with_metrics, tiny_config

STEPS = 3
LR = configs.default().lr

ROWS = {
    'harsh: lr x10, r1_gamma 100, tau low end, 95% drops': dict(
        config=dict(lr=10 * LR, r1_gamma=100.0, tau=gumbel.TAU_RANGE[0]), drop_rate=0.95),
    'mild: lr x0.1, r1_gamma 0, tau high end, no drops': dict(
        config=dict(lr=0.1 * LR, r1_gamma=0.0, tau=gumbel.TAU_RANGE[1]), drop_rate=0.0),
    'batch 1 per device': dict(config=dict(batch_size=4), devices=4),
}


def _leaves(tree):
  return np.concatenate([np.ravel(v) for v in jax.tree.leaves(tree)])


@pytest.mark.parametrize('row', list(ROWS))
def test_training_at_the_extremes_is_finite_and_moves(row):
  spec = ROWS[row]
  config = tiny_config(**spec.get('config', {}))
  configs.validate(config)  # each row is a setting a user may give
  devices = jax.devices()[:spec.get('devices', 1)]
  assert config.batch_size // len(devices) == (1 if 'devices' in spec else config.batch_size)
  rates = None if 'drop_rate' not in spec else [spec['drop_rate']] * config.batch_size
  init, final, records = run_with_metrics(STEPS, devices, config, rates)
  for i, m in enumerate(records):
    bad = {k: v for k, v in m.items() if not np.isfinite(v)}
    assert not bad, f'step {i + 1}: {bad}'
  for k in ('g', 'd', 'ema'):
    after = _leaves(final[k])
    assert np.isfinite(after).all(), k
    assert np.abs(after - _leaves(init[k])).max() > 0, f'{k} did not move'
  for loss in ('loss_d', 'loss_g'):
    values = [m[loss] for m in records]
    assert max(values) - min(values) > 1e-6, f'{loss} stayed at {values}'
  if 'drop_rate' in spec:  # the data's drops reach the step as given
    assert records[0]['real_drop_rate'] == pytest.approx(spec['drop_rate'], abs=0.02)
