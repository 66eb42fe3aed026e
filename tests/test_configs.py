"""A config is checked once, where it is loaded: configs.validate. What is
built from a valid config (Setup, DropOptions) reads its fields as they are,
so validate refuses a config that lacks one, naming it, instead of letting a
default stand in for it."""

import ml_collections
import pytest

from dusty_jax import configs
from train_helpers import tiny_config


def test_every_experiment_config_is_complete():
  configs.validate(tiny_config())
  for name in ('baseline', 'dusty1', 'dusty2_drops', 'dusty1_rangedrops', 'dusty1_headdrops',
               'dusty1_detdrops'):
    configs.validate(configs.study(name))


@pytest.mark.parametrize('path', ['drop_const', 'tolerance', 'ema_rampup', 'drops',
                                  'sensor.width', 'drops.rate_by', 'data.dir'])
def test_a_missing_field_is_refused_by_name(path):
  c = tiny_config()
  *groups, last = path.split('.')
  node = c
  for g in groups:
    node = node[g]
  del node[last]
  with pytest.raises(configs.ConfigError, match=(
      rf'^config field {path} is missing: build experiment configs on '
      r'dusty_jax\.configs\.default\(\)')):
    configs.validate(c)


def test_a_config_not_built_on_the_defaults_names_its_first_gap():
  """The first missing field in ConfigDict's (sorted) order."""
  c = ml_collections.ConfigDict({'seed': 0, 'model': 'dusty1'})
  with pytest.raises(configs.ConfigError, match='config field adam_eps is missing'):
    configs.validate(c)


def test_an_old_run_read_through_load_is_complete(tmp_path):
  """configs.load translates an old run's config (configs.upgrade): the
  fields it predates then hold their legacy values, so the checks and the
  Setup can read them."""
  c = tiny_config()
  for f in ('eqlr', 'augment_style', 'drop_const', 'drops'):
    del c[f]
  configs.save(str(tmp_path), c)
  loaded = configs.load(str(tmp_path))
  configs.validate(loaded)
  assert (loaded.eqlr, loaded.augment_style, loaded.drop_const) == ('fan_in', 'symmetric',
                                                                    -1.0)
  assert loaded.drops.to_dict() == configs.drop_defaults().to_dict()
