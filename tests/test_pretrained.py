"""Generators shipped in the package: export/load round trip, and inversion
with the trained study model where it is present."""


import jax
import numpy as np
import pytest

import dusty_jax
from dusty_jax import codec, generator, pretrained, trainer
from train_helpers import tiny_config


@pytest.mark.parametrize('model', ['baseline', 'dusty2'])
def test_export_load_round_trip(tiny, tmp_path, model):
  setup = trainer.make_setup(tiny_config(model=model), tiny)
  state = trainer.init_state(setup, jax.random.key(0))
  params = trainer.generator_params(setup, state.g_params, tiny.nominal_angles(),
                                    tolerance=0.0125)
  path = pretrained.export(params, 'tiny', source='test', directory=str(tmp_path))
  back = generator.load_file(path)
  assert (back.settings, back.sensor, back.tolerance) == (params.settings, params.sensor,
                                                         0.0125)
  z = jax.random.normal(jax.random.key(1), (3, params.latent_dim))
  a = dusty_jax.generate(params, z, jax.random.key(2))
  b = dusty_jax.generate(back, z, jax.random.key(2))
  for k in ('inv_depth', 'measurability', 'scan'):
    np.testing.assert_array_equal(np.asarray(a[k]), np.asarray(b[k]))


def test_the_package_ships_the_four_models_users_need():
  """The baseline, the faithful DUSty-I and the drops variants of DUSty-I and
  DUSty-II; the research steps between them are in git history."""
  assert pretrained.available() == ['sim-baseline', 'sim-dusty1', 'sim-dusty1-authors',
                                    'sim-dusty2']


def test_unknown_name_lists_available():
  with pytest.raises(ValueError, match='available'):
    dusty_jax.load_pretrained('no-such-model')


# Measured when the model was exported (0.19 and 0.51 for this scene); a
# constant far prediction scores 15.4 and 11.3.
FIT_ABS_REL_BOUND = 0.3
COMPLETION_ABS_REL_BOUND = 0.8
# The shipped models' measurability against held-out scenes' observed drops
# (sim-dusty1, six scenes from the encoder + 50 iterations: 0.855 when
# exported; the faithful sim-dusty1-authors 0.221; a constant scores 0.5);
# within rings on surfaces < 40 m, sim-dusty1 0.526 (a per-ring rate: 0.5).
AUC_BOUND = 0.75
WITHIN_RING_BOUND = 0.51


@pytest.mark.slow
def test_trained_dusty1_fits_and_completes_a_held_out_simulated_scan():
  """The shipped DUSty-I, trained on simulated scenes, inverts a scene it
  never saw (scene seed outside every split of the study's data)."""
  from dusty_jax.data import simulated_lidar
  from dusty_jax.metrics import ground_truth
  params = dusty_jax.load_pretrained('sim-dusty1-authors')
  s = simulated_lidar.render_scan(7_000_001, params.sensor)
  target = codec.encode(s.depth, params.sensor)
  rec = dusty_jax.invert(params, target, num_steps=300, key=jax.random.key(0))
  g = ground_truth.disentanglement(params.sensor, rec['inv_depth'][None],
                                   rec['measurability'][None], s.depth[None],
                                   s.complete[None], s.drop_prob[None])
  assert g['completion']['pixels'] > 500
  assert g['fit']['abs_rel'] < FIT_ABS_REL_BOUND
  assert g['completion']['abs_rel'] < COMPLETION_ABS_REL_BOUND


@pytest.mark.slow
def test_shipped_sim_dusty1_keeps_and_places_its_drops():
  """sim-dusty1 is DUSty-I trained as the authors' code trains (the main
  command, experiments/synthetic.py), then its drop levels fitted per (ring,
  depth) cell (drops preset 'levels', fitted to inversions of training
  scans), with its encoder. The faithful training stops dropping
  (sim-dusty1-authors: about 1e-4); the levels alone bring its samples near
  the data's drop rate (0.20; 0.213 of 16 samples when exported), and from
  the encoder + 50 iterations its measurability ranks six held-out scenes'
  observed drops (AUC 0.889 when exported), within rings on surfaces nearer
  than 40 m too (0.514; a per-ring rate scores 0.5, the retired `far`
  preset's ranking ran backwards there)."""
  from dusty_jax import configs
  from dusty_jax.data import synthetic
  from dusty_jax.metrics import ground_truth
  training = pretrained.describe('sim-dusty1')['training']
  assert training['config'] == 'experiments/synthetic.py'
  trained = training['drops']
  assert trained == dict(configs.drop_defaults().to_dict(), depth_levels=True)
  assert 'train_encoder' in training['encoder']
  assert pretrained.describe('sim-dusty1-authors').get('training') is None
  # The main command's config today still trains this model: same network,
  # schedule, batch, seed, augmentation and drops.
  import importlib.util
  import os
  path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                      training['config'])
  spec = importlib.util.spec_from_file_location('main_config', path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  config = module.get_config()
  settings = dusty_jax.load_pretrained('sim-dusty1').settings
  assert (config.model, config.latent_dim, config.ch_base, config.ch_max) == (
      settings.model, settings.latent_dim, settings.ch_base, settings.ch_max)
  assert (config.num_steps, config.batch_size, config.seed, config.augment) == (
      training['steps'], training['batch_size'], training['seed'], training['augment'])
  assert config.drops.to_dict() == trained
  rates = {}
  for name in ('sim-dusty1', 'sim-dusty1-authors'):
    out = dusty_jax.sample(dusty_jax.load_pretrained(name), jax.random.key(0), 16)
    rates[name] = 1.0 - float(np.mean(out['mask']))
  assert 0.1 < rates['sim-dusty1'] < 0.3 and rates['sim-dusty1-authors'] < 0.01, rates
  params = dusty_jax.load_pretrained('sim-dusty1')
  assert params.settings.depth_levels and params.encoder is not None
  obs, complete, drop_prob = synthetic.simulate(6, params.sensor, seed=7, progress=False)
  rec = dusty_jax.invert(params, codec.encode(obs, params.sensor), init='encoder',
                         num_steps=50)
  scores = ground_truth.measurability_scores(params.sensor, np.asarray(rec['measurability']),
                                             obs, complete, drop_prob)
  assert scores['auc'] > AUC_BOUND, scores['auc']
  assert scores['auc_near_within_ring'] > WITHIN_RING_BOUND, scores['auc_near_within_ring']


@pytest.mark.slow
def test_shipped_sim_dusty2_keeps_and_places_its_drops():
  """sim-dusty2 is DUSty-II trained with the same dips variant, its drop
  levels fitted per (ring, depth) cell after training: it drops about as
  often as the simulated data (0.231 of 16 samples when exported; data
  0.20) and, inverted from a random start (it ships without an encoder),
  ranks a held-out scene's observed drops (AUC 0.906 when exported, 100
  iterations)."""
  from dusty_jax import pretrained
  from dusty_jax.data import synthetic
  from dusty_jax.metrics import ground_truth
  training = pretrained.describe('sim-dusty2')['training']
  assert training['config'] == 'experiments/study.py:dusty2,dips,cpu'
  assert training['drops']['dip_weight'] > 0 and training['drops']['depth_levels']
  params = dusty_jax.load_pretrained('sim-dusty2')
  assert params.model == 'dusty2' and params.encoder is None
  assert params.settings.depth_levels
  rate = 1.0 - float(np.mean(dusty_jax.sample(params, jax.random.key(0), 16)['mask']))
  assert 0.1 < rate < 0.3, rate
  obs, _, _ = synthetic.simulate(2, params.sensor, seed=7, progress=False)
  rec = dusty_jax.invert(params, codec.encode(obs, params.sensor), num_steps=100,
                         key=jax.random.key(0))
  valid = np.asarray(codec.valid_depth(obs, params.sensor))
  auc = ground_truth.roc_auc(np.asarray(rec['measurability']), valid)
  assert auc > AUC_BOUND, auc
