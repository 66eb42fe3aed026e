"""A config is checked once, where it is loaded: configs.validate. What is
built from a valid config (Setup, DropOptions) reads its fields as they are,
so validate refuses a config that lacks one, naming it, instead of letting a
default stand in for it."""

import json
import os
import re

import ml_collections
import pytest

from dusty_jax import cli, configs
from train_helpers import STUDY, tiny_config


EXPERIMENTS = os.path.join(os.path.dirname(__file__), '..', 'experiments')


def test_every_experiment_config_is_complete():
  configs.validate(tiny_config())
  for model in ('dusty1', 'dusty2'):
    for preset in STUDY['PRESETS']:
      for scale in STUDY['SCALES']:
        configs.validate(STUDY['study'](model, preset, scale))
  configs.validate(STUDY['study']('baseline'))


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
  assert c.to_dict() == STUDY['study'](*want).to_dict()
  assert c.model == want[0] and c.latent_dim == (128 if want[2] == 'cpu' else 512)
  assert c.drops.to_dict() == dict(configs.drop_defaults().to_dict(),
                                   **STUDY['PRESETS'][want[1]])


@pytest.mark.parametrize('args, what', [(('dusty3',), 'model'), (('dusty1', 'channel'), 'preset'),
                                        (('dusty1', 'levels', 'gpu'), 'scale')])
def test_an_unknown_study_name_lists_the_known_ones(args, what):
  with pytest.raises(configs.ConfigError, match=rf'^unknown study {what} .*; known: \w+, '):
    STUDY['study'](*args)


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


def test_a_run_config_of_this_version_loads_as_saved(tmp_path):
  """configs.load gives a run's config as saved (with trained_on beside
  default()'s fields); fields added since it was written take their
  defaults, which do what such runs did (after_training: both steps;
  data.memory_mb, data.allow_changed)."""
  c = tiny_config()
  c.after_training = 'final_evaluation'
  configs.save(str(tmp_path), c)
  loaded = configs.load(str(tmp_path))
  configs.validate(loaded)
  assert loaded.to_dict() == c.to_dict()
  saved = json.loads((tmp_path / configs.FILE).read_text())
  del saved['after_training'], saved['data']['memory_mb'], saved['data']['allow_changed']
  (tmp_path / configs.FILE).write_text(json.dumps(dict(saved, trained_on={'devices': 2})))
  loaded = configs.load(str(tmp_path))
  configs.validate(loaded)
  assert loaded.after_training == 'levels,final_evaluation' == configs.default().after_training
  assert loaded.data.memory_mb == configs.default().data.memory_mb
  assert loaded.data.allow_changed is False and loaded.data.dir == c.data.dir
  assert loaded.trained_on.devices == 2


@pytest.mark.parametrize('change, says', [
    (lambda d: d.pop('eqlr'), 'field eqlr is missing'),
    (lambda d: d.pop('augment_style'), 'field augment_style is missing'),
    (lambda d: d.update(drop_const=-1.0), 'field drop_const is no field of this version'),
    (lambda d: d['drops'].update(rate_by='ring_depth'),
     'field drops.rate_by is no field of this version')])
def test_a_research_era_run_config_is_one_line(tmp_path, change, says):
  """A config that holds a field since removed, or lacks one whose default
  changed when it came, is of a research-era run: refused in one line naming
  the field and the last version that reads it, not translated."""
  configs.save(str(tmp_path), tiny_config())
  saved = json.loads((tmp_path / configs.FILE).read_text())
  change(saved)
  (tmp_path / configs.FILE).write_text(json.dumps(saved))
  with pytest.raises(configs.ConfigError, match=(
      rf'^{re.escape(str(tmp_path / configs.FILE))}: {says}; written by a research-era '
      r'dusty_jax; dusty_jax 0\.1\.0 is the last version that reads it$')):
    configs.load(str(tmp_path))
