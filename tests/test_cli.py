"""The command lines: every error a user's input causes is one line on stderr
and a non-zero exit; Ctrl-C and a full disk say what a rerun does."""

import contextlib
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import FAST_COMPILE

HERE = os.path.dirname(__file__)
SMOKE = os.path.join(HERE, '..', 'experiments', 'smoke.py')


def _env(tmp_path, devices=1):
  env = dict(os.environ, DUSTY_JAX_CACHE=str(tmp_path / 'cache'))
  if devices == 1:
    env['XLA_FLAGS'] = FAST_COMPILE  # no forced count: the trainer's (use_cpu_cores)
  return env


def _messages(stderr: str):
  """stderr's lines without the progress bar's (tqdm) frames."""
  lines = re.split(r'[\r\n]+', stderr)
  return [l for l in lines if l.strip() and not re.search(r'\d+%\|', l)]


def _one_error_line(res, status):
  lines = _messages(res.stderr)
  assert res.returncode == status, res.stderr[-3000:]
  assert len(lines) == 1 and lines[0].startswith('error: '), res.stderr[-3000:]
  return lines[0]


def test_unknown_config_field_names_the_nearest(tmp_path):
  """One line with difflib's nearest field, exit 2 as absl's bad flags."""
  cmd = [sys.executable, '-m', 'dusty_jax.train', '--config', SMOKE,
         '--workdir', str(tmp_path / 'w')]
  res = subprocess.run(cmd + ['--config.data.dri=data/kitti'], env=_env(tmp_path),
                       capture_output=True, text=True, timeout=300)
  assert _one_error_line(res, 2) == ('error: unknown config field data.dri; did you '
                                     'mean data.dir?')
  res = subprocess.run(cmd + ['--config.batchsize=4'], env=_env(tmp_path),
                       capture_output=True, text=True, timeout=300)
  assert _one_error_line(res, 2) == ('error: unknown config field batchsize; did you '
                                     'mean batch_size?')
  assert not (tmp_path / 'w').exists()


def test_a_failed_command_leaves_no_async_noise_after_its_line(capsys, caplog):
  """A user error is one line, even where the failed work left an asyncio
  task whose exception nobody retrieved (orbax's writes on a full disk): its
  log record, emitted when the task is collected, is dropped."""
  import asyncio
  import gc
  from dusty_jax import cli, errors

  def fails():
    loop = asyncio.new_event_loop()

    async def write():
      raise OSError(28, 'No space left on device')
    task = loop.create_task(write())
    loop.run_until_complete(asyncio.sleep(0.01))
    loop.close()
    assert task.done()
    raise errors.UserError('no space left on device while writing checkpoint 6')

  level = logging.getLogger('asyncio').level
  try:
    with pytest.raises(cli.Exit):
      cli.run(fails)
    gc.collect()
  finally:
    logging.getLogger('asyncio').setLevel(level)
  assert capsys.readouterr().err.strip().splitlines() == [
      'error: no space left on device while writing checkpoint 6']
  assert not [r for r in caplog.records if r.name == 'asyncio']


@pytest.mark.parametrize('value,shown', [('1', True), ('yes', True), ('0', False),
                                         ('off', False), ('', False), (None, False)])
def test_dusty_jax_traceback_asks_for_tracebacks_unless_it_says_no(monkeypatch, capsys,
                                                                  value, shown):
  """One owner reads DUSTY_JAX_TRACEBACK (errors.show_traceback); '0' means
  no, as for the other DUSTY_JAX_ switches (it used to mean yes)."""
  from dusty_jax import cli, errors

  def fails():
    raise errors.UserError('bad input')

  if value is None:
    monkeypatch.delenv(errors.TRACEBACK_ENV, raising=False)
  else:
    monkeypatch.setenv(errors.TRACEBACK_ENV, value)
  assert errors.show_traceback() is shown
  with pytest.raises(errors.UserError if shown else cli.Exit):
    cli.run(fails)
  assert capsys.readouterr().err.strip() == ('' if shown else 'error: bad input')


def test_unknown_field_message():
  import ml_collections
  from dusty_jax import cli
  c = ml_collections.ConfigDict({'lr': 0.1, 'data': {'dir': '', 'seed': 0}})
  assert cli.unknown_field(c, 'data.dir') is None
  assert cli.unknown_field(c, 'data.sed') == ('unknown config field data.sed; did you '
                                              'mean data.seed?')
  assert cli.unknown_field(c, 'zzzz') == 'unknown config field zzzz'
  assert 'lr is a value' in cli.unknown_field(c, 'lr.x')


def _wrong_shape_data(tmp_path):
  d = tmp_path / 'wrong'
  d.mkdir()
  np.save(d / 'train.npy', np.ones((3, 8, 8), np.float32))
  return f'--config.data.dir={d}'


# (arguments, devices, exit status, what the one line says).
BAD = [
    (['--config.sensor.preset=hdl64'], 1, 2, r"sensor\.preset='hdl64'.*kitti, mpo"),
    (['--config.batch_size=6'], 4, 2, r'batch_size=6: is not divisible by the 4 devices'),
    ([_wrong_shape_data], 1, 1, r'train\.npy: array of shape \(3, 8, 8\) does not match'),
    (['--config.batch_size=0'], 1, 2, r'batch_size=0: must be a whole number >= 1'),
    (['--config.lr=-1'], 1, 2, r'lr=-1'),
    (['--config.model=dusty3'], 1, 2, r'model=.dusty3.'),
    (['--config.data.dir=/nonexistent'], 1, 1, r'dusty_jax\.tools\.prepare'),
    (['--config.batch_size=abc'], 1, 2, r'--config\.batch_size=abc'),
    (['--config=nonexistent.py'], 1, 2, r'nonexistent\.py: no such config file'),
    (['--nosuchflag'], 1, 2, r"Unknown command line flag 'nosuchflag'"),
    (['extra'], 1, 2, r'unexpected arguments'),
    ([f'--config={os.path.join(os.path.dirname(SMOKE), "study.py")}:dusty1,lvls'], 1, 2,
     r"study\.py:dusty1,lvls: unknown study preset 'lvls'; known: authors, levels, dips$"),
    ([f'--config={SMOKE}:foo'], 1, 2,
     r"smoke\.py:foo: this config takes no argument after ':' \(got 'foo'\); experiments/study"),
    (['--config.impl=XLA'], 1, 2, r"impl='XLA': must be '' .*, 'matmul' or 'xla'$"),
    (['--config.augment=cutout,flip'], 1, 2, r"augment='cutout,flip': 'flip' is no augm"),
    (['--config.drops=dips'], 1, 2,
     r'drops is a group of fields .* \(the drops presets: --config experiments/study\.py:'),
    (['--config.model=baseline', '--config.drops.depth_levels=True'], 1, 2,
     r'set drops\.depth_levels=False, or train it with --config experiments/study\.py:baseline'),
    ([lambda t: (t / 'f').write_text('') or f'--workdir={t / "f"}'], 1, 1,
     r'/f: a file, not a directory; give a run directory'),
]


@pytest.mark.parametrize('args, devices, status, says', BAD,
                         ids=[re.sub(r'\W+', '_', getattr(a[0], '__name__', str(a[0])))[:40]
                              for a, *_ in BAD])
def test_bad_config_is_one_line(tmp_path, args, devices, status, says):
  args = [a(tmp_path) if callable(a) else a for a in args]
  res = subprocess.run([sys.executable, '-m', 'dusty_jax.train', '--config', SMOKE,
                        '--workdir', str(tmp_path / 'w')] + args,
                       env=_env(tmp_path, devices), capture_output=True, text=True,
                       timeout=300)
  assert re.search(says, _one_error_line(res, status))
  assert not (tmp_path / 'w').exists()


# A tool's flag value that cannot be right is a bad flag as absl's own are:
# (tool, arguments, what the line says), exit 2 before anything loads.
BAD_TOOL_FLAGS = [
    ('invert', ['--corrupt', 'drops:0.9'], r"--corrupt=drops:0\.9: unknown corruption 'drops'"),
    ('invert', ['--corrupt', 'noise:-1'], r'fraction of the sensor.s depth range, not metres'),
    ('invert', ['--split', 'test'], r'give exactly one of --input and --split'),
    ('prepare', ['--splits', 'train,tset'], r'--splits=.*each split is one of train, val, test'),
    ('synthesize', ['--sensor', 'hdl64'], r'--sensor=hdl64: a sensor preset \(hdl32e, hdl64e, kitti.*\) or an existing sensor spec file'),
    ('prepare', ['--sensor', 'vlp32'], r'--sensor=vlp32: a sensor preset \(.*vlp16\), an existing sensor spec file, or auto'),
    ('evaluate', ['--num', '1'], r'--num=1: 1 is not integer >= 2'),
]
TOOL_ARGS = {'invert': ['--workdir', 'sim-dusty1', '--input', 'x.npy'],
             'prepare': ['--dataset', 'kitti', '--root', '.', '--out', 'o'],
             'synthesize': ['--num', '2', '--out', 'o'],
             'evaluate': ['--workdir', 'sim-dusty1']}


@pytest.mark.parametrize('tool, args, says', BAD_TOOL_FLAGS,
                         ids=[f'{t}_{a[0][2:]}' for t, a, _ in BAD_TOOL_FLAGS])
def test_a_bad_tool_flag_value_is_exit_2(tmp_path, capsys, tool, args, says):
  import importlib
  main = importlib.import_module(f'dusty_jax.tools.{tool}').main
  with pytest.raises(SystemExit) as e:
    main(TOOL_ARGS[tool] + args)
  assert e.value.code == 2
  err = capsys.readouterr().err.strip()
  assert err.startswith('error: ') and '\n' not in err and re.search(says, err), err
  assert not (tmp_path / 'o').exists() and not os.path.exists('o')


@contextlib.contextmanager
def _training(tmp_path, workdir, *extra, prefix=()):
  """A training that runs until stopped; killed on the way out, so that a
  failed test leaves nothing running."""
  cmd = list(prefix) + [
      sys.executable, '-m', 'dusty_jax.train', '--config', SMOKE, '--workdir', workdir,
      '--config.num_steps=100000', '--config.checkpoint_every=2',
      '--config.log_every=1', '--config.image_every=100000',
      '--config.data.num_synthetic=16'] + list(extra)
  # SIGINT as a terminal delivers it: a shell starting this suite in the
  # background leaves it ignored, the child inherits that, and Python then
  # never raises KeyboardInterrupt. (Set here, not in a preexec_fn: a fork
  # of this threaded process must not run Python.)
  ignored = signal.getsignal(signal.SIGINT) == signal.SIG_IGN
  if ignored:
    signal.signal(signal.SIGINT, signal.SIG_DFL)
  try:
    proc = subprocess.Popen(cmd, env=_env(tmp_path), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=os.path.join(HERE, '..'))
  finally:
    if ignored:
      signal.signal(signal.SIGINT, signal.SIG_IGN)
  try:
    yield proc
  finally:
    proc.kill()
    proc.wait()
    proc.stdout.close()
    proc.stderr.close()


@pytest.mark.slow
def test_ctrl_c_is_one_line_and_exit_130(tmp_path):
  """The step, the checkpoint a rerun resumes from; no traceback."""
  workdir = tmp_path / 'w'
  saved = lambda: [int(s) for s in os.listdir(workdir / 'checkpoints') if s.isdigit()]
  with _training(tmp_path, str(workdir)) as proc:
    deadline = time.time() + 500
    while not (workdir / 'checkpoints').is_dir() or max(saved(), default=0) < 4:
      assert proc.poll() is None, proc.communicate()[1][-3000:]
      assert time.time() < deadline, 'no checkpoint within the time allowed'
      time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)
  assert proc.returncode == 130, err[-3000:]
  lines = _messages(err)
  assert 'Traceback' not in err and len(lines) == 1, err[-3000:]
  m = re.fullmatch(r'interrupted at step (\d+); the last checkpoint is step (\d+); '
                   r'rerun the same command to resume', lines[0])
  assert m, lines
  step, last = int(m.group(1)), int(m.group(2))
  assert last >= 4 and step >= last
  assert max(saved()) == last


def _can_mount_tmpfs():
  if not shutil.which('unshare'):
    return False
  res = subprocess.run(['unshare', '--mount', 'sh', '-c',
                        'mount -t tmpfs -o size=1m tmpfs /mnt'], capture_output=True)
  return res.returncode == 0


@pytest.mark.skipif(not _can_mount_tmpfs(), reason='needs unshare and tmpfs mounts '
                    '(root or user namespaces) to fill a disk')
@pytest.mark.slow
def test_full_disk_during_a_checkpoint_is_one_line(tmp_path):
  """A 2 MB disk holds two checkpoints of the smoke run; writing the
  third fails. One line: which checkpoint, which are intact, what to do."""
  disk = tmp_path / 'disk'
  disk.mkdir()
  workdir = str(disk / 'w')
  script = (f'mount -t tmpfs -o size=2m tmpfs {disk} && exec "$@"')
  with _training(tmp_path, workdir, prefix=('unshare', '--mount', 'sh', '-c', script,
                                           'sh')) as proc:
    _, err = proc.communicate(timeout=600)
  line = _messages(err)
  assert proc.returncode == 1 and len(line) == 1, err[-3000:]
  m = re.fullmatch(r'error: no space left on device while writing checkpoint (\d+) in '
                   r'\S+/checkpoints; (?:step|steps) ([\d, and]+) (?:is|are) intact; '
                   r'free space and rerun to resume from (\d+)', line[0])
  assert m, line
  intact = [int(s) for s in re.findall(r'\d+', m.group(2))]
  assert intact == sorted(intact) and int(m.group(3)) == intact[-1]
  assert int(m.group(1)) > intact[-1]
