"""A config is checked once, where it is loaded: configs.validate. What is
built from a valid config (Setup, DropOptions) reads its fields as they are,
so validate refuses a config that lacks one, naming it, instead of letting a
default stand in for it."""

import json
import os

import ml_collections
import pytest

from dusty_jax import cli, configs, drops
from train_helpers import tiny_config


EXPERIMENTS = os.path.join(os.path.dirname(__file__), '..', 'experiments')


def test_every_experiment_config_is_complete():
  configs.validate(tiny_config())
  for model in ('dusty1', 'dusty2'):
    for preset in drops.PRESETS:
      for scale in configs.STUDY_SCALES:
        configs.validate(configs.study(model, preset, scale))
  configs.validate(configs.study('baseline'))


@pytest.mark.parametrize('name', sorted(f[:-3] for f in os.listdir(EXPERIMENTS)
                                        if f.endswith('.py')))
def test_every_experiment_file_loads_a_valid_config(name):
  c = cli._load_config(os.path.join(EXPERIMENTS, name + '.py'))
  assert c is not None, f'experiments/{name}.py does not load'
  configs.validate(c)


@pytest.mark.parametrize('arg, want', [
    ('', ('dusty1', 'authors', 'cpu')), ('dusty2', ('dusty2', 'authors', 'cpu')),
    ('dusty1,levels,cpu', ('dusty1', 'levels', 'cpu')), ('baseline,,paper', ('baseline', 'authors',
                                                                       'paper')),
    (' dusty2 , dips ', ('dusty2', 'dips', 'cpu'))])
def test_the_study_file_takes_model_preset_and_scale(arg, want):
  path = os.path.join(EXPERIMENTS, 'study.py') + (f':{arg}' if arg else '')
  c = cli._load_config(path)
  assert c.to_dict() == configs.study(*want).to_dict()
  assert c.model == want[0] and c.latent_dim == (128 if want[2] == 'cpu' else 512)
  assert c.drops.to_dict() == dict(configs.drop_defaults().to_dict(), **drops.PRESETS[want[1]])


@pytest.mark.parametrize('args, what', [(('dusty3',), 'model'), (('dusty1', 'channel'), 'preset'),
                                        (('dusty1', 'levels', 'gpu'), 'scale')])
def test_an_unknown_study_name_lists_the_known_ones(args, what):
  with pytest.raises(configs.ConfigError, match=rf'^unknown study {what} .*; known: \w+, '):
    configs.study(*args)


@pytest.mark.parametrize('path', ['r1_every', 'tolerance', 'ema_rampup', 'drops',
                                  'sensor.width', 'drops.rate_weight', 'data.dir'])
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
  for f in ('eqlr', 'augment_style', 'drops'):
    del c[f]
  configs.save(str(tmp_path), c)
  loaded = configs.load(str(tmp_path))
  configs.validate(loaded)
  assert (loaded.eqlr, loaded.augment_style) == ('fan_in', 'symmetric')
  # drop_const left the library: runs that kept ALPHA (-1) load without it.
  saved = json.loads((tmp_path / configs.FILE).read_text())
  for value, loads in ((-1.0, True), (-2.0, False)):
    (tmp_path / configs.FILE).write_text(json.dumps(dict(saved, drop_const=value)))
    if loads:
      assert 'drop_const' not in configs.load(str(tmp_path))
    else:
      with pytest.raises(configs.ConfigError, match=(
          r'^config field drop_const=-2\.0: this option was removed; commit '
          rf"{configs.LAST_WITH['drop_const']} is the last that has it$")):
        configs.load(str(tmp_path))
  assert loaded.drops.to_dict() == configs.drop_defaults().to_dict()
