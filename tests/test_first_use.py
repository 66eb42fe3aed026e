"""A newcomer's first calls stay quick and plain: a second process reuses
the compilation cache, `import dusty_jax` stays light, a pretrained name works
where a run directory is taken, and a mistake ends in one short error."""

import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time
import zlib

import numpy as np
import pytest

import dusty_jax
from dusty_jax import cli, encoder_trainer, inversion, pretrained, xla_cache
from dusty_jax.data import pipeline
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
import dusty_jax
print(dusty_jax.enable_compilation_cache())
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
    assert xla_cache.directory() == os.path.join(pipeline.default_cache(), 'xla') == where
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


# A library user's program that never asks for the cache: JAX's cache
# settings before and after each public call (a tiny DUSty-I of random
# weights with an encoder, as tests/test_extremes.py's), then after the
# program asks.
_LIBRARY_CALLS = '''
import json, os
import jax, jax.numpy as jnp, numpy as np
import dusty_jax
from dusty_jax import encoder, generator
from dusty_jax.models import ModelSettings
from dusty_jax.sensor import tiny_sensor
NAMES = ('jax_compilation_cache_dir', 'jax_persistent_cache_min_compile_time_secs',
         'jax_persistent_cache_min_entry_size_bytes', 'jax_enable_compilation_cache')
seen = {}
def note(what):
  seen[what] = {n: getattr(jax.config, n) for n in NAMES}
note('start')
dusty_jax.load_pretrained('sim-dusty1')
note('load_pretrained')
sensor = tiny_sensor(16, 64)
settings = ModelSettings(model='dusty1', latent_dim=16, ch_base=8, ch_max=16)
params = generator.GeneratorParams(
    variables=settings.generator(sensor).init(jax.random.key(0), jnp.zeros((1, 16))),
    angles=jnp.asarray(sensor.nominal_angles(), jnp.float32), sensor=sensor, settings=settings)
enc_settings = encoder.EncoderSettings(ch_base=4, ch_max=8, hidden=16)
params = params.replace(encoder=encoder.Encoder(sensor, 16, enc_settings, 'xla').init(
    jax.random.key(1), jnp.zeros((1,) + sensor.shape)), encoder_settings=enc_settings)
scans = dusty_jax.sample(params, jax.random.key(2), 2)['scan']
note('sample')
dusty_jax.generate(params, np.zeros((2, 16), np.float32), jax.random.key(3))
note('generate')
encoder.encode(params, scans)
note('encode')
dusty_jax.invert(params, scans, num_steps=2, init='encoder')
dusty_jax.invert(params, scans, num_steps=2)
note('invert')
made = os.listdir(os.environ['DUSTY_JAX_CACHE'])
dusty_jax.enable_compilation_cache()
note('asked')
print(json.dumps({'settings': seen, 'made': made}))
'''


def test_library_calls_leave_the_cache_settings_as_they_were(tmp_path):
  """Importing dusty_jax and calling it switches no cache on; the program's
  own call does, and so does a command line's start."""
  out = _python(_LIBRARY_CALLS, {'DUSTY_JAX_CACHE': str(tmp_path)}, drop=_OWN_CACHE)
  seen, made = json.loads(out.splitlines()[-1]).values()
  start = seen.pop('start')
  assert start['jax_compilation_cache_dir'] is None  # JAX's default: no cache
  asked = seen.pop('asked')
  assert seen == {call: start for call in ('load_pretrained', 'sample', 'generate', 'encode',
                                           'invert')}
  assert made == []  # nothing written under the dusty_jax cache
  assert asked == dict(start, jax_compilation_cache_dir=str(tmp_path / 'xla'),
                       jax_persistent_cache_min_compile_time_secs=xla_cache.MIN_COMPILE_SECS)
  # A command line switches it on where it starts (train and every tool run
  # through cli.run).
  code = ('import jax\nfrom dusty_jax import cli\n'
          'cli.run(lambda: print(jax.config.jax_compilation_cache_dir))')
  assert _python(code, {'DUSTY_JAX_CACHE': str(tmp_path / 'cli')},
                 drop=_OWN_CACHE).split() == [str(tmp_path / 'cli' / 'xla')]


def _entries(folder):
  return {p.name: p.read_bytes() for p in folder.glob('*' + xla_cache.ENTRY_SUFFIX)}


def _stderr_lines(code: str, env: dict, prefix=()):
  """(stdout's words, stderr's lines) of ``code`` run in a fresh process."""
  full = {k: v for k, v in os.environ.items() if k != 'JAX_COMPILATION_CACHE_DIR'}
  full.update(env, XLA_FLAGS=FAST_COMPILE, PYTHONPATH=os.path.abspath(REPO))
  r = subprocess.run([*prefix, sys.executable, '-c', code], env=full, capture_output=True,
                     text=True, timeout=300)
  assert r.returncode == 0, r.stderr[-3000:]
  return r.stdout.split(), r.stderr.splitlines()


def test_a_damaged_entry_is_deleted_and_written_again(tmp_path):
  env = {'DUSTY_JAX_CACHE': str(tmp_path), 'JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS': '0'}
  first, _ = _stderr_lines(_COMPILE, env)
  folder = tmp_path / 'xla'
  written = _entries(folder)
  assert len(written) >= 2 and all(map(xla_cache.readable, written.values())), written.keys()
  # Since the last check, one entry cut short, another overwritten; others
  # intact.
  cut, overwritten, *intact = sorted(written)
  (folder / cut).write_bytes(written[cut][:len(written[cut]) // 2])
  (folder / overwritten).write_bytes(np.random.default_rng(0).bytes(2000))
  checked, changed = time.time() - 100, time.time() - 50
  os.utime(folder / xla_cache.CHECKED, (checked, checked))
  for name in written:
    os.utime(folder / name, (changed, changed))
  out, err = _stderr_lines(_COMPILE, env)
  assert out == first
  assert err == [f'removed 2 damaged entries of the compilation cache {folder} (JAX could '
                 'not read them); their programs are compiled and written again'], err
  again = _entries(folder)
  assert sorted(again) == sorted(written)  # written anew, under the same keys
  assert all(map(xla_cache.readable, again.values()))
  assert all(again[name] == written[name] for name in intact)  # JAX's own entries pass
  # The next process finds nothing to say.
  out, err = _stderr_lines(_COMPILE, env)
  assert out == first and err == [] and _entries(folder) == again


def test_an_entry_damaged_just_now_is_repaired_at_once_one_being_written_kept(tmp_path):
  """An unreadable entry written just now is read again after SETTLE_S: the
  one left as it was is damaged and goes (with its access-time file), the
  one whose write completes meanwhile stays."""
  good = zlib.compress(bytes(100))
  (tmp_path / 'a-cache').write_bytes(good)
  (tmp_path / 'b-cache').write_bytes(good[:5])  # damaged just now
  (tmp_path / 'b-atime').write_bytes(bytes(8))
  (tmp_path / 'c-cache').write_bytes(good[:5])  # being written
  finish = threading.Timer(xla_cache.SETTLE_S / 4, (tmp_path / 'c-cache').write_bytes, (good,))
  finish.start()
  try:
    assert xla_cache.remove_damaged(str(tmp_path)) == ['b-cache']
  finally:
    finish.join()
  assert sorted(os.listdir(tmp_path)) == [xla_cache.CHECKED, 'a-cache', 'c-cache']
  assert (tmp_path / 'c-cache').read_bytes() == good
  # One damaged since the last check, and older than SETTLE_S: it goes too.
  (tmp_path / 'a-cache').write_bytes(b'junk')
  os.utime(tmp_path / 'a-cache', (time.time() - 1, time.time() - 1))
  assert xla_cache.remove_damaged(str(tmp_path)) == ['a-cache']


# In a cache where a new file fails as on a read-only mount (the tests may
# run as root, whom chmod does not stop): a program the cache holds and a new
# one, counting the programs read from the cache (jax.monitoring).
_REFUSE = '''
import errno, tempfile
def refuse(*args, **kwargs):
  raise OSError(errno.EROFS, 'Read-only file system')
tempfile.mkstemp = refuse
'''
_COUNT_HITS = '''
import jax, jax.numpy as jnp
from dusty_jax import xla_cache
hits = []
jax.monitoring.register_event_listener(
    lambda name, **kw: hits.append(name) if name.endswith('cache_hits') else None)
print(xla_cache.enable())
print(jax.jit(lambda x: jnp.sin(x) * 2 + 1)(jnp.arange(5.0)).sum())
print(jax.jit(lambda x: jnp.cos(x) * 3)(jnp.arange(4.0)).sum(), len(hits))
'''


def _read_only_line(folder):
  return (f'the compilation cache {folder} cannot be written: programs found there are '
          'used, new ones are compiled in each process; make it writable, or set '
          'DUSTY_JAX_CACHE to a folder you can write')


def test_an_unwritable_cache_is_one_line_and_the_run_goes_on(tmp_path):
  env = {'DUSTY_JAX_CACHE': str(tmp_path), 'JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS': '0'}
  folder = tmp_path / 'xla'
  _stderr_lines(_COMPILE, env)
  written = _entries(folder)
  # Read-only: the program it holds is read, nothing is written, one line.
  out, err = _stderr_lines(_REFUSE + _COUNT_HITS, env)
  assert out[0] == str(folder) and int(out[-1]) >= 1  # read from the cache
  assert _entries(folder) == written
  assert err == [_read_only_line(folder)], err
  # A cache folder that cannot be made (a file in its place): compiled as
  # without a cache, one line.
  other = tmp_path / 'other'
  other.mkdir()
  (other / 'xla').write_text('not a folder')
  out, err = _stderr_lines(_COMPILE, {'DUSTY_JAX_CACHE': str(other)})
  assert out[0] == out[2] == 'None' and float(out[1]) == pytest.approx(7.2701716)
  assert len(err) == 1 and err[0].startswith(f'the compilation cache {other / "xla"} cannot '
                                             'be made ('), err


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
  assert steps == [str(encoder_trainer.TrainOptions().steps)]


def test_encoder_training_without_scans_for_its_real_term_is_refused(shipped, tmp_path):
  with pytest.raises(ValueError, match=r'w_real=1.0: the real-scan term needs'):
    encoder_trainer.train(shipped[1], str(tmp_path / 'enc'),
                          encoder_trainer.TrainOptions(steps=1))


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


def _can_mount_read_only(tmp_path):
  if not shutil.which('unshare'):
    return False
  return subprocess.run(['unshare', '--mount', 'sh', '-c', f'mount --bind {tmp_path} '
                         f'{tmp_path} && mount -o remount,ro,bind {tmp_path}'],
                        capture_output=True).returncode == 0


def test_a_cache_on_a_read_only_mount_is_read_and_left_alone(tmp_path):
  """As above, on a real read-only bind mount (where unshare may mount):
  JAX's own 'Error writing persistent compilation cache entry' warnings
  stay away too."""
  if not _can_mount_read_only(tmp_path):
    pytest.skip('needs unshare and bind mounts (root or user namespaces)')
  env = {'DUSTY_JAX_CACHE': str(tmp_path), 'JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS': '0'}
  _stderr_lines(_COMPILE, env)
  folder = tmp_path / 'xla'
  written = _entries(folder)
  mount = (f'mount --bind {folder} {folder} && mount -o remount,ro,bind {folder} && '
           'exec "$@"')
  out, err = _stderr_lines(_COUNT_HITS, env, prefix=('unshare', '--mount', 'sh', '-c',
                                                     mount, 'sh'))
  assert out[0] == str(folder) and int(out[-1]) >= 1
  assert err == [_read_only_line(folder)], err
  assert _entries(folder) == written
