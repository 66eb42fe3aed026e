"""A newcomer's first calls stay quick and plain: a second process reuses
the compilation cache, `import dusty_jax` stays light, a pretrained name works
where a run directory is taken, and a mistake ends in one short error."""

import dataclasses
import os
import re
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dusty_jax
from dusty_jax import cli, codec, encoder, inversion, models, pretrained, sampling, xla_cache
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


def _raise(*args, **kwargs):
  raise AssertionError('traced and exported again')


def _kept(folder):
  return sorted(p.name for p in folder.rglob('*' + xla_cache.EXPORT_SUFFIX))


def _decode():
  """codec.decode kept on disk, as a new process would wrap it."""
  return xla_cache.jit(codec.decode, static_argnames=('sensor', 'tolerance'))


def _same(got, want):
  for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
    np.testing.assert_array_equal(a, b)


@pytest.fixture
def kept_in(tmp_path, monkeypatch):
  """Kept programs go under tmp_path (as under a JAX cache folder a user named)."""
  monkeypatch.setitem(xla_cache._state, 'done', True)
  monkeypatch.setitem(xla_cache._state, 'directory', str(tmp_path))
  return tmp_path / xla_cache.OWN_EXPORT_FOLDER


def test_a_traced_program_is_kept_and_read_back(kept_in, monkeypatch):
  # A folder of another source, unused for longer than STALE_DAYS, goes when
  # this source's folder is made; a recent one stays.
  old, recent = kept_in / ('0' * 16), kept_in / ('1' * 16)
  for folder in (old, recent):
    folder.mkdir(parents=True)
  long_ago = time.time() - (xla_cache.STALE_DAYS + 1) * 86400
  os.utime(old, (long_ago, long_ago))
  x = jnp.linspace(-1.0, 1.0, 12).reshape(3, 4)
  want = codec.decode(x, 'kitti')
  fn = _decode()
  _same(fn(x, 'kitti'), want)
  (written,) = _kept(kept_in)
  assert written.startswith('dusty_jax.codec.decode-')
  assert not old.exists() and recent.exists()
  # A new wrapper (what a new process has) reads the file instead of tracing.
  real_export = jax.export.export
  monkeypatch.setattr(jax.export, 'export', _raise)
  again = _decode()
  _same(again(x, sensor='kitti'), want)
  assert len(again.programs) == 1
  # Inside traced code, and under disable_jit, it is jax.jit: nothing new kept.
  _same(jax.jit(lambda y: again(y, 'kitti'))(x), want)
  with jax.disable_jit():
    _same(again(x[:1], 'kitti'), codec.decode(x[:1], 'kitti'))
  assert len(again.programs) == 1 and _kept(kept_in) == [written]
  # A torn file is traced again and rewritten.
  monkeypatch.setattr(jax.export, 'export', real_export)
  (path,) = kept_in.rglob(written)
  path.write_bytes(b'torn')
  _same(_decode()(x, 'kitti'), want)
  assert path.stat().st_size > 100
  # A new shape, dtype or static argument is another program, in its own file;
  # writing it removes the .tmp file of a write cut short, not one in progress.
  cut, writing = path.parent / 'cut.tmp', path.parent / 'writing.tmp'
  for f in (cut, writing):
    f.write_bytes(b'part')
  hours_ago = time.time() - 2 * xla_cache.STALE_TMP_S
  os.utime(cut, (hours_ago, hours_ago))
  before = set(kept_in.rglob('*' + xla_cache.EXPORT_SUFFIX))
  _same(fn(x[:2], 'kitti'), codec.decode(x[:2], 'kitti'))
  (other,) = set(kept_in.rglob('*' + xla_cache.EXPORT_SUFFIX)) - before
  assert not cut.exists() and writing.exists()
  writing.unlink()
  _same(fn(x, 'kitti', 0.25), codec.decode(x, 'kitti', 0.25))
  _same(fn(x, 'mpo'), codec.decode(x, 'mpo'))
  assert len(_kept(kept_in)) == 4
  # A kept program that reads but does not run here (another shape's, say):
  # jax.jit's trace instead, and the file goes (the next process keeps anew).
  path.write_bytes(other.read_bytes())
  _same(_decode()(x, 'kitti'), want)
  assert not path.exists()


def test_programs_are_not_kept_where_they_could_be_stale(kept_in, monkeypatch, shipped):
  params = shipped[0]
  key = jax.random.key(3)
  want = sampling._sample.jitted(params, key, 2, None)
  _same(dusty_jax.sample(params, key, 2), want)
  assert [n.split('-')[0] for n in _kept(kept_in)] == ['dusty_jax.sampling._sample']
  # A static field of the params (tau) is in the key: a new program.
  warmer = params.replace(settings=dataclasses.replace(params.settings, tau=0.5))
  _same(dusty_jax.sample(warmer, key, 2), sampling._sample.jitted(warmer, key, 2, None))
  assert len(_kept(kept_in)) == 2
  # A variant a user replaced is traced each time, never kept.
  with monkeypatch.context() as m:
    m.setitem(models.VARIANTS, 'dusty1', dataclasses.replace(models.VARIANTS['dusty1']))
    _same(dusty_jax.sample(params, key, 3), sampling._sample.jitted(params, key, 3, None))
  assert len(_kept(kept_in)) == 2
  # A constant a user set: the source no longer says what runs.
  zeros = jnp.zeros((2, 2))
  with monkeypatch.context() as m:
    m.setattr(inversion, 'NOISE_SCALE', 0.0)
    assert xla_cache.patched()
    fn = _decode()
    _same(fn(zeros, 'kitti'), codec.decode(zeros, 'kitti'))
    assert not fn.programs and len(_kept(kept_in)) == 2
  assert not xla_cache.patched()
  _same(_decode()(zeros, 'kitti'), codec.decode(zeros, 'kitti'))
  assert len(_kept(kept_in)) == 3  # the same call, unpatched, is kept
  # Source changed since the package was loaded: the digest stands for nothing.
  monkeypatch.setattr(dusty_jax, '_loaded_at', 0.0)
  assert xla_cache.source_digest() is None
  fn = _decode()
  _same(fn(zeros[:1], 'kitti'), codec.decode(zeros[:1], 'kitti'))
  assert not fn.programs and len(_kept(kept_in)) == 3


def test_kept_programs_are_off_with_the_cache(kept_in, monkeypatch):
  monkeypatch.setitem(xla_cache._state, 'directory', None)  # as with ..._CACHE=0
  fn = _decode()
  _same(fn(jnp.zeros(3), 'kitti'), codec.decode(jnp.zeros(3), 'kitti'))
  assert not fn.programs and not kept_in.parent.joinpath('export').exists()
  assert not kept_in.exists()


# invert() in a process of its own, twice (one scan from a random start; the
# same scan with a mask, one key per scan, from the encoder): 'write' (cache
# empty), 'read' (jax.export unusable: the programs must come from the files)
# or 'off'.
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
a = dusty_jax.invert(params, scan, num_steps=3)['inv_depth']
mask = np.zeros(scan.shape, bool)
mask[:, ::2] = scan[:, ::2] > -1
b = dusty_jax.invert(params, scan[None], mask=mask[None], init='encoder', num_steps=2,
                     key=jax.random.split(jax.random.key(5), 1))['inv_depth'][0]
np.save(out, np.stack([a, b]))
print(len(inversion._start.programs), len(inversion._search.programs))
"""


def test_a_second_process_inverts_from_the_kept_programs_bit_for_bit(tmp_path):
  env = dict(os.environ, XLA_FLAGS=FAST_COMPILE, PYTHONPATH=os.path.abspath(REPO),
             DUSTY_JAX_CACHE=str(tmp_path))
  env.pop('JAX_COMPILATION_CACHE_DIR')  # kept under DUSTY_JAX_CACHE, as for a user
  kept = {}
  for mode in ('write', 'read', 'off'):
    if mode == 'off':
      env['DUSTY_JAX_COMPILATION_CACHE'] = '0'
    r = subprocess.run([sys.executable, '-c', _INVERT, mode, str(tmp_path / f'{mode}.npy')],
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    kept[mode] = r.stdout.split()
  assert kept == {'write': ['2', '1'], 'read': ['2', '1'], 'off': ['0', '0']}
  names = sorted(n.split('-')[0] for n in _kept(tmp_path / 'export'))
  assert names == ['dusty_jax.inversion._search'] + ['dusty_jax.inversion._start'] * 2
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
  assert r.returncode == 0, r.stderr  # as the tools' --help
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
