"""A newcomer's first calls (issue 36): the compilation cache, light imports,
pretrained names where a run directory is taken, and the small errors."""

import os
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dusty_jax
from dusty_jax import cli, codec, encoder, inversion, pretrained, xla_cache
from dusty_jax.data import pipeline
from dusty_jax.sensor import get_sensor
from dusty_jax.tools import train_encoder
from conftest import FAST_COMPILE

REPO = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..')


def _python(code: str, env_update: dict, drop=(), cwd=None):
  env = {k: v for k, v in os.environ.items() if k not in drop}
  env.update(env_update, XLA_FLAGS=FAST_COMPILE, PYTHONPATH=os.path.abspath(REPO))
  r = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                     text=True, timeout=300, cwd=cwd)
  assert r.returncode == 0, r.stderr[-3000:]
  return r.stdout


# A program that compiles, then what JAX's cache settings are.
_COMPILE = '''
import jax, jax.numpy as jnp
from dusty_jax import xla_cache
print(xla_cache.enable())
print(jax.jit(lambda x: jnp.sin(x) * 2 + 1)(jnp.arange(5.0)).sum())
print(jax.config.jax_compilation_cache_dir)
print(jax.config.jax_persistent_cache_min_compile_time_secs)
'''
_OWN_CACHE = ('JAX_COMPILATION_CACHE_DIR', 'JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS')


def test_compiled_programs_go_under_the_dusty_jax_cache(tmp_path):
  out = _python(_COMPILE, {'DUSTY_JAX_CACHE': str(tmp_path)}, drop=_OWN_CACHE).split()
  where = str(tmp_path / 'xla')
  assert out[0] == where and out[2] == where
  assert float(out[3]) == xla_cache.MIN_COMPILE_SECS
  # The cache root is the data pipeline's, under the same variable.
  os.environ['DUSTY_JAX_CACHE'], old = str(tmp_path), os.environ.get('DUSTY_JAX_CACHE')
  try:
    assert xla_cache.cache_root() == pipeline.default_cache() == str(tmp_path)
  finally:
    os.environ.pop('DUSTY_JAX_CACHE') if old is None else os.environ.update(
        DUSTY_JAX_CACHE=old)


def test_a_program_compiled_once_is_written_and_read_back(tmp_path):
  env = {'DUSTY_JAX_CACHE': str(tmp_path),
         'JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS': '0'}
  _python(_COMPILE, env, drop=('JAX_COMPILATION_CACHE_DIR',))
  written = sorted(os.listdir(tmp_path / 'xla'))
  assert any(f.startswith('jit_') for f in written), written
  _python(_COMPILE, env, drop=('JAX_COMPILATION_CACHE_DIR',))
  assert sorted(os.listdir(tmp_path / 'xla')) == written  # found, not compiled anew


def test_the_cache_is_off_when_asked_and_a_users_own_is_kept(tmp_path):
  off = _python(_COMPILE, {'DUSTY_JAX_CACHE': str(tmp_path),
                           'DUSTY_JAX_COMPILATION_CACHE': '0'}, drop=_OWN_CACHE).split()
  assert off[0] == 'None' and off[2] == 'None' and not (tmp_path / 'xla').exists()
  own = str(tmp_path / 'mine')
  kept = _python(_COMPILE, {'DUSTY_JAX_CACHE': str(tmp_path), 'JAX_COMPILATION_CACHE_DIR': own,
                            'JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS': '3'}).split()
  assert kept[0] == own and kept[2] == own and float(kept[3]) == 3
  assert not (tmp_path / 'xla').exists()


def _affine(x, scale, how):
  return x * scale + (1.0 if how == 'plus' else -1.0)


def _raise(*args, **kwargs):
  raise AssertionError('traced and exported again')


def test_a_traced_program_is_kept_and_read_back(tmp_path, monkeypatch):
  monkeypatch.setenv('DUSTY_JAX_CACHE', str(tmp_path))
  kept = tmp_path / 'export'
  fn = xla_cache.jit(_affine, static_argnames=('how',))
  x = jnp.arange(4.0)
  np.testing.assert_array_equal(fn(x, 2.0, 'plus'), x * 2 + 1)
  (written,) = os.listdir(kept)
  assert written.startswith('test_first_use._affine-')
  # A new wrapper (what a new process has) reads the file instead of tracing.
  real_export = jax.export.export
  monkeypatch.setattr(jax.export, 'export', _raise)
  again = xla_cache.jit(_affine, static_argnames=('how',))
  np.testing.assert_array_equal(again(x, 2.0, how='plus'), x * 2 + 1)
  assert len(again.programs) == 1 and os.listdir(kept) == [written]
  # Inside traced code it inlines, as jax.jit does: nothing is read or kept.
  np.testing.assert_array_equal(jax.jit(lambda y: again(y, 3.0, 'minus'))(x), x * 3 - 1)
  assert len(again.programs) == 1
  # A torn file is traced again and rewritten.
  monkeypatch.setattr(jax.export, 'export', real_export)
  (kept / written).write_bytes(b'torn')
  torn = xla_cache.jit(_affine, static_argnames=('how',))
  np.testing.assert_array_equal(torn(x, 2.0, 'plus'), x * 2 + 1)
  assert (kept / written).stat().st_size > 100
  # A new shape, dtype or static argument is another program, in its own file.
  fn(jnp.arange(5.0), 2.0, 'plus')
  fn(jnp.arange(4), 2, 'plus')
  fn(x, 2.0, 'minus')
  assert len(os.listdir(kept)) == 4
  # Calls the predicate refuses are traced each process, never kept.
  only_plus = xla_cache.jit(_affine, static_argnames=('how',),
                            exportable=lambda how: how == 'plus')
  np.testing.assert_array_equal(only_plus(x, 1.0, 'minus'), x - 1)
  assert not only_plus.programs and len(os.listdir(kept)) == 4
  # Files an older dusty_jax source wrote go when a new one is written.
  stale = kept / 'test_first_use._affine-000000000000-0.jaxexport'
  stale.write_bytes(b'old')
  fn(jnp.arange(6.0), 2.0, 'plus')
  assert not stale.exists() and len(os.listdir(kept)) == 5


def test_kept_programs_are_off_with_the_cache(tmp_path, monkeypatch):
  monkeypatch.setitem(xla_cache._state, 'done', True)
  monkeypatch.setitem(xla_cache._state, 'directory', None)  # as with ..._CACHE=0
  monkeypatch.setenv('DUSTY_JAX_CACHE', str(tmp_path))
  fn = xla_cache.jit(_affine, static_argnames=('how',))
  np.testing.assert_array_equal(fn(jnp.arange(3.0), 2.0, 'plus'), jnp.arange(3.0) * 2 + 1)
  assert not fn.programs and not (tmp_path / 'export').exists()


# invert() of one scan in a process of its own: 'write' (cache empty), 'read'
# (jax.export unusable: the search must come from the file) or 'off'.
_INVERT = """
import sys
import jax, numpy as np
import dusty_jax
from dusty_jax import codec, inversion
from dusty_jax.data import simulated_lidar
mode, out = sys.argv[1:]
if mode == 'read':
  jax.export.export = None
params = dusty_jax.load_pretrained('sim-dusty1')
scan = codec.encode(simulated_lidar.render_scan(7, params.sensor).depth, params.sensor)
res = dusty_jax.invert(params, scan, num_steps=3)
np.save(out, np.asarray(res['inv_depth']))
print(len(inversion._start.programs), len(inversion._search.programs))
"""


def test_a_second_process_inverts_from_the_kept_program_bit_for_bit(tmp_path):
  env = dict(os.environ, XLA_FLAGS=FAST_COMPILE, PYTHONPATH=os.path.abspath(REPO),
             DUSTY_JAX_CACHE=str(tmp_path))
  kept = {}
  for mode in ('write', 'read', 'off'):
    if mode == 'off':
      env['DUSTY_JAX_COMPILATION_CACHE'] = '0'
    r = subprocess.run([sys.executable, '-c', _INVERT, mode, str(tmp_path / f'{mode}.npy')],
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    kept[mode] = r.stdout.split()
  assert kept == {'write': ['1', '1'], 'read': ['1', '1'], 'off': ['0', '0']}
  names = sorted(f.split('-')[0] for f in os.listdir(tmp_path / 'export'))
  assert names == ['dusty_jax.inversion._search', 'dusty_jax.inversion._start']
  want = np.load(tmp_path / 'off.npy')
  for mode in ('write', 'read'):
    np.testing.assert_array_equal(np.load(tmp_path / f'{mode}.npy'), want)


def test_import_and_tool_help_load_no_jax():
  code = '''
import sys
import dusty_jax
assert 'jax' not in sys.modules, 'import dusty_jax'
from dusty_jax.tools import convert, evaluate, invert, synthesize
for tool in (convert, evaluate, invert, synthesize):
  try:
    tool.main(['--help'])
  except SystemExit as e:
    assert e.code == 0
  assert 'jax' not in sys.modules, tool.__name__
print(sorted(dusty_jax.__all__))
print(dusty_jax.invert.__module__, dusty_jax.load_checkpoint.__name__)
'''
  out = _python(code, {}).splitlines()
  assert out[-2] == str(sorted(dusty_jax.__all__))
  assert out[-1] == 'dusty_jax.inversion load'
  assert dusty_jax.invert is inversion.invert
  with pytest.raises(AttributeError, match="no attribute 'nvert'"):
    dusty_jax.nvert  # noqa: B018


def test_codec_takes_a_preset_name_or_says_what_it_takes():
  depth = np.random.default_rng(0).uniform(0.5, 130, (4, 8)).astype(np.float32)
  kitti = get_sensor('kitti')
  np.testing.assert_array_equal(codec.encode(depth, 'kitti'), codec.encode(depth, kitti))
  x = codec.encode(depth, kitti)
  for a, b in zip(codec.decode(x, 'kitti'), codec.decode(x, kitti)):
    np.testing.assert_array_equal(a, b)
  with pytest.raises(ValueError, match=r"unknown sensor 'hdl'; known presets"):
    codec.encode(depth, 'hdl')
  with pytest.raises(TypeError, match=r'sensor: expected a SensorSpec.*got int'):
    codec.encode(depth, 64)


@pytest.fixture(scope='module')
def shipped():
  return dusty_jax.load_pretrained('sim-dusty1'), dusty_jax.load_pretrained('sim-dusty2')


def test_a_scan_of_the_wrong_shape_is_named_as_given(shipped):
  params = shipped[0]
  h, w = params.sensor.shape
  with pytest.raises(ValueError, match=re.escape(f'scan of shape ({h}, {w}, 1) does not '
                                                 f"match the generator's sensor ({h}, {w})")):
    dusty_jax.invert(params, np.zeros((h, w, 1), np.float32), num_steps=1)
  with pytest.raises(ValueError, match=re.escape(f'scan of shape (2, {h}, {w + 1})')):
    dusty_jax.invert(params, np.zeros((2, h, w + 1), np.float32), num_steps=1)


def test_pretrained_names_in_load_checkpoint_and_the_encoder_error(shipped):
  with pytest.raises(FileNotFoundError,
                     match=r"pretrained model: load it with dusty_jax\.load_pretrained\('sim-dusty1'\)"):
    dusty_jax.load_checkpoint('sim-dusty1')
  with pytest.raises(FileNotFoundError, match='not a training run directory'):
    dusty_jax.load_checkpoint('sim-dusty9')  # no such name: the run directory's message
  h, w = shipped[1].sensor.shape
  carry = [n for n in ('sim-dusty1', 'sim-dusty2') if 'encoder' in pretrained.describe(n)]
  assert carry == ['sim-dusty1']  # as shipped: the message below names it
  with pytest.raises(ValueError, match=r"has no encoder.*init='random'.*the pretrained "
                     r"[^;]*sim-dusty1[^;]* carr"):
    dusty_jax.invert(shipped[1], np.full((h, w), -0.5, np.float32), init='encoder')


def test_tools_take_a_pretrained_name(shipped, tmp_path, capsys):
  from dusty_jax import tools
  from dusty_jax.tools import evaluate, invert
  params, config = tools.load_model('sim-dusty1')
  assert config is None
  np.testing.assert_array_equal(params.angles, shipped[0].angles)
  with pytest.raises(FileNotFoundError, match=r"sim-dusty9: no such run directory or file, "
                     r"nor a pretrained model; give .*sim-dusty1"):
    tools.load_model('sim-dusty9')
  with pytest.raises(SystemExit, match=r"sim-dusty2 has no encoder.*sim-dusty1") as e:
    invert.main(['--workdir', 'sim-dusty2', '--init', 'encoder', '--input',
                 str(tmp_path / 'scans')])
  assert e.value.code == 1
  with pytest.raises(SystemExit, match=r'sim-dusty1: no config.json.*--data_dir'):
    evaluate.main(['--workdir', 'sim-dusty1'])
  for tool in (invert, evaluate):
    with pytest.raises(SystemExit):
      tool.main(['--help'])
    assert 'sim-dusty1' in capsys.readouterr().out


def test_train_encoder_usage_names_its_default_steps():
  steps = re.findall(r'--steps (\d+)', train_encoder.__doc__)
  assert steps == [str(encoder.TrainOptions().steps)]


def test_encoder_training_without_scans_for_its_real_term_is_refused(shipped, tmp_path):
  with pytest.raises(ValueError, match=r'w_real=1.0: the real-scan term needs'):
    encoder.train(shipped[1], str(tmp_path / 'enc'), encoder.TrainOptions(steps=1))


def test_train_help_lists_the_configs_and_their_fields():
  env = dict(os.environ, XLA_FLAGS=FAST_COMPILE)
  r = subprocess.run([sys.executable, '-m', 'dusty_jax.train', '--help'], cwd=REPO,
                     env=env, capture_output=True, text=True, timeout=300)
  text = ' '.join(r.stdout.split())
  names = [f[:-3] for f in os.listdir(os.path.join(REPO, 'experiments'))
           if f.endswith('.py') and not f.startswith('_')]
  assert names and all(re.search(rf'\b{n}\b', text) for n in names), text
  assert '--config.FIELD=VALUE' in text
  for field in ('batch_size', 'num_steps', 'data.{', 'model'):
    assert field in text, field


def test_a_relative_config_path_works_from_any_directory(tmp_path):
  found = cli.find_config('experiments/smoke.py')
  assert os.path.samefile(found, os.path.join(REPO, 'experiments', 'smoke.py'))
  assert cli.find_config('experiments/smoke.py:arg').endswith('smoke.py:arg')
  assert cli.find_config('nonexistent.py') == 'nonexistent.py'
  env = dict(os.environ, XLA_FLAGS=FAST_COMPILE, PYTHONPATH=os.path.abspath(REPO))
  base = [sys.executable, '-m', 'dusty_jax.train', '--workdir', str(tmp_path / 'run')]
  # The config loads from elsewhere: its validation speaks, not a missing file.
  r = subprocess.run(base + ['--config', 'experiments/smoke.py', '--config.batch_size=0'],
                     cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
  assert r.returncode == 2 and 'batch_size=0: must be' in r.stderr, r.stderr[-2000:]
  r = subprocess.run(base + ['--config=experiments/smok.py'], cwd=tmp_path, env=env,
                     capture_output=True, text=True, timeout=300)
  assert r.returncode == 2 and 'no such config file, here or in' in r.stderr
  assert 'smoke.py' in r.stderr
