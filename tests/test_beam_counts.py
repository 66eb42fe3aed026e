"""Any number of beams: the networks run on the rows rounded up to a multiple
of 16, and nothing a user reads has more rows than the sensor."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dusty_jax
from dusty_jax import codec, encoder, metrics, models, restorer, trainer
from dusty_jax.codec import ALPHA
from dusty_jax.sensor import tiny_sensor
from train_helpers import tiny_config

SETTINGS = models.ModelSettings('dusty1', latent_dim=8, ch_base=4, ch_max=8)


@pytest.mark.parametrize('rows', [1, 8, 20, 40, 130])
def test_generator_outputs_exactly_the_sensor_s_rows(rows):
  g = SETTINGS.generator(tiny_sensor(rows, 32))
  z = jnp.ones((2, 8))
  out = jax.eval_shape(g.apply, jax.eval_shape(g.init, jax.random.key(0), z), z)
  assert out.shape == (2, rows, 32, 2)


def test_the_extra_rows_are_cut_below_the_lowest_beam():
  # 40 beams run on 48 rows: the same parameters as a 48-beam sensor's,
  # whose first 40 rows are the 40-beam generator's outputs.
  g40, g48 = SETTINGS.generator(tiny_sensor(40, 32)), SETTINGS.generator(tiny_sensor(48, 32))
  z = jax.random.normal(jax.random.key(1), (2, 8))
  params = g48.init(jax.random.key(0), z)
  np.testing.assert_array_equal(g40.apply(params, z), g48.apply(params, z)[:, :40])


def test_the_discriminator_sees_the_extra_rows_as_no_returns():
  d40, d48 = SETTINGS.discriminator(tiny_sensor(40, 32)), SETTINGS.discriminator(tiny_sensor(48, 32))
  x = jax.random.uniform(jax.random.key(2), (3, 40, 32), minval=-1, maxval=1)
  params = d48.init(jax.random.key(0), jnp.zeros((1, 48, 32)))
  padded = jnp.concatenate([x, jnp.full((3, 8, 32), ALPHA)], axis=1)
  np.testing.assert_allclose(d40.apply(params, x), d48.apply(params, padded), rtol=1e-6)
  # ... and its gradient reaches the sensor's rows only, every one of them.
  grad = jax.grad(lambda s: d40.apply(params, s).sum())(x)
  assert grad.shape == x.shape and (jnp.abs(grad).sum(axis=(0, 2)) > 0).all()


def test_the_encoder_and_the_restorer_take_any_rows():
  e = encoder.Encoder(tiny_sensor(20, 32), latent_dim=8,
                      settings=encoder.EncoderSettings(ch_base=4, ch_max=8, hidden=8))
  scans = jnp.zeros((2, 20, 32))
  assert jax.eval_shape(e.apply, jax.eval_shape(e.init, jax.random.key(0), scans),
                        scans).shape == (2, 8)
  s = restorer.Settings(width=4)
  x = jnp.zeros((1, 10, 32, 5))
  sel = restorer.Selector(s)
  assert jax.eval_shape(sel.apply, jax.eval_shape(sel.init, jax.random.key(0), x),
                        x).shape == (1, 10, 32, s.num_candidates)


@pytest.mark.slow
@pytest.mark.parametrize('rows', [40, 20])
def test_a_sensor_of_any_rows_trains_samples_inverts_restores_and_evaluates(rows, tmp_path):
  config = tiny_config(num_steps=2, log_every=1, image_every=2, checkpoint_every=2)
  config.sensor.height = rows
  workdir = str(tmp_path / 'run')
  trainer.train_and_evaluate(config, workdir, log=lambda m: None)
  params, _ = dusty_jax.load_checkpoint(workdir)
  out = dusty_jax.sample(params, jax.random.key(0), 3)
  for k in ('scan', 'inv_depth', 'measurability'):
    assert np.shape(out[k]) == (3, rows, 64), k
  scans = np.asarray(out['scan'])
  assert np.isfinite(scans).all()
  inv = dusty_jax.invert(params, scans[0], num_steps=2)
  assert np.shape(inv['inv_depth']) == (rows, 64)
  depth = np.asarray(codec.decode(scans[0], params.sensor)[0])
  known = np.zeros(depth.shape, bool)
  known[::2] = True
  for method in ('linear', 'inversion'):
    out = dusty_jax.restore(params, depth, known, method=method, num_steps=2)
    assert np.shape(out['depth']) == (rows, 64), method
  fake = np.asarray(dusty_jax.sample(params, jax.random.key(1), 4)['scan'])
  m = metrics.compare(np.concatenate([scans, scans[:1]]), fake, params.angles,
                      sensor=params.sensor, num_points=64, seed=0)
  assert all(np.isfinite(v) for v in jax.tree.leaves(m) if isinstance(v, float))
  assert os.listdir(os.path.join(workdir, 'images'))
