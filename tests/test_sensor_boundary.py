"""A sensor is resolved once, where a program starts: a command's flags
(sensor.get_sensor) or the trainer's config (configs.validate). Below that,
the codec, the writers, the metrics and the data preparation take a
SensorSpec only, and refuse a name with a TypeError saying what to pass."""

import importlib
import inspect
import os
import pkgutil
import re

import numpy as np
import pytest

from dusty_jax import codec, configs, metrics, sensor as sensor_lib, trainer, writers
from dusty_jax.data import prepare
from dusty_jax.metrics import clouds, ground_truth, protocol, reconstruction, records
from dusty_jax.metrics import restoration
from dusty_jax.sensor import PRESETS, tiny_sensor
from train_helpers import tiny_config

SPEC = tiny_sensor(4, 8)
REFUSED = re.escape("sensor: expected a SensorSpec (params.sensor, or dusty_jax.get_sensor"
                    "('kitti') for a preset or a spec file), got str 'kitti'")


def _modules():
  """codec, writers and every module of metrics/."""
  names = ['dusty_jax.codec', 'dusty_jax.writers'] + [
      f'dusty_jax.metrics.{m.name}' for m in pkgutil.iter_modules(metrics.__path__)]
  return [importlib.import_module(n) for n in names]


def _sensor_parameters() -> dict:
  """{module.function: the annotation of its ``sensor`` parameter, as written}
  of every function those modules define (classes' methods too)."""
  out = {}
  for module in _modules():
    functions = [(n, f) for n, f in inspect.getmembers(module, inspect.isfunction)]
    for _, cls in inspect.getmembers(module, inspect.isclass):
      functions += [(f'{cls.__name__}.{n}', f)
                    for n, f in inspect.getmembers(cls, inspect.isfunction)]
    for name, fn in functions:
      if fn.__module__ != module.__name__:
        continue
      p = inspect.signature(fn).parameters.get('sensor')
      if p is not None:
        a = p.annotation
        out[f'{module.__name__}.{name}'] = a if isinstance(a, str) else getattr(
            a, '__name__', repr(a))
  return out


def test_codec_writers_and_metrics_annotate_their_sensor_as_a_spec():
  found = _sensor_parameters()
  # The ones this test must see, so that it cannot pass by finding none.
  assert {'dusty_jax.codec.encode', 'dusty_jax.codec.decode', 'dusty_jax.codec.valid_depth',
          'dusty_jax.codec.complete_depth', 'dusty_jax.writers.scan_figure',
          'dusty_jax.writers.range_image', 'dusty_jax.metrics.protocol.compare',
          'dusty_jax.metrics.clouds.scans_to_clouds',
          'dusty_jax.metrics.ground_truth.completion'} <= set(found)
  bad = {k: a for k, a in found.items() if a not in ('SensorSpec', 'SensorSpec | None')}
  assert not bad, f'sensor parameters not annotated SensorSpec: {bad}'
  assert not hasattr(codec, 'as_sensor')


def _scans(n=2):
  return np.random.default_rng(0).uniform(-1, 1, (n,) + SPEC.shape).astype(np.float32)


def _figure(sensor):
  return writers.scan_figure([writers.Column('a', writers.DEPTH, _scans(1))], sensor)


# Each takes the sensor last; with the spec each runs, with its name each refuses.
CALLS = {
    'codec.encode': lambda s: codec.encode(np.full(SPEC.shape, 5.0), s),
    'codec.decode': lambda s: codec.decode(_scans(), s),
    'codec.valid_depth': lambda s: codec.valid_depth(np.full(SPEC.shape, 5.0), s),
    'codec.complete_depth': lambda s: codec.complete_depth(_scans(), s),
    'writers.range_image': lambda s: writers.range_image(_scans()[0], s),
    'writers.scan_figure': _figure,
    'metrics.clouds.scans_to_clouds': lambda s: clouds.scans_to_clouds(
        _scans(), SPEC.nominal_angles(), s),
    'metrics.ground_truth.ring_keep_rate': lambda s: ground_truth.ring_keep_rate(
        np.full((2,) + SPEC.shape, 5.0), s),
    'metrics.reconstruction.completion_errors': lambda s: reconstruction.completion_errors(
        {'inv_depth': _scans()}, np.full((2,) + SPEC.shape, 5.0), s),
    'metrics.restoration.edges': lambda s: restoration.edges(np.full(SPEC.shape, 5.0), s),
    'metrics.records.sensor_record': records.sensor_record,
}


@pytest.mark.parametrize('name', sorted(CALLS))
def test_a_sensor_name_is_refused_below_the_boundary(name):
  CALLS[name](SPEC)
  with pytest.raises(TypeError, match=f'^{REFUSED}$'):
    CALLS[name]('kitti')


def test_the_metrics_protocol_and_prepare_refuse_a_name_before_any_work(tmp_path):
  real = _scans(2)
  with pytest.raises(TypeError, match=f'^{REFUSED}$'):
    protocol.compare(real, real, SPEC.nominal_angles(), sensor='kitti', num_points=4)
  (tmp_path / 'raw').mkdir()
  with pytest.raises(TypeError, match=f'^{REFUSED}$'):
    prepare.prepare('files', str(tmp_path / 'raw'), str(tmp_path / 'out'), 'kitti')
  with pytest.raises(ValueError, match='give a sensor or auto_sensor=True, not both'):
    prepare.prepare('files', str(tmp_path / 'raw'), str(tmp_path / 'out'), PRESETS['vlp16'],
                    auto_sensor=True)
  assert not (tmp_path / 'out').exists()


def test_a_config_names_its_sensor_once_and_validate_resolves_it():
  c = configs.default()
  assert 'spec' not in c.sensor  # a run records its spec in generator.json alone
  assert configs.validate(c) == PRESETS['kitti']
  c.sensor.width = 512
  assert configs.validate(c) == sensor_lib.with_columns(PRESETS['kitti'], 512)


@pytest.mark.slow
def test_training_reads_the_configs_sensor_once(tmp_path, monkeypatch):
  """The trainer resolves the config's sensor at its start, and every step
  of the run (the resume check, the data, the records, the step) takes that
  spec; a second start of the finished run reads it once too."""
  calls = []
  resolve = sensor_lib.from_config
  monkeypatch.setattr(sensor_lib, 'from_config', lambda cfg: calls.append(1) or resolve(cfg))
  config = tiny_config(num_steps=1, checkpoint_every=1, log_every=1, image_every=1000)
  config.data.cache = str(tmp_path / 'cache')
  config.data.num_synthetic = 16
  config.after_training = ''
  workdir = str(tmp_path / 'run')
  for _ in range(2):
    trainer.train_and_evaluate(config, workdir, log=lambda m: None)
    assert len(calls) == 1
    calls.clear()
  with open(os.path.join(workdir, configs.FILE)) as f:
    assert '"spec"' not in f.read()
