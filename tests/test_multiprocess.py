"""A run of several processes: it resumes after losing one, the survivor ends
in one line, and a run directory has one writer (a second training started
on it refuses in one line and writes nothing).

The 2-process runs are the training command on experiments/smoke.py, each
process with one CPU device, talking over localhost.
"""

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

from dusty_jax import checkpoint, errors, levels, parallel
from conftest import FAST_COMPILE

# Trainings of several processes (minutes on 2 cores): the slow set.
pytestmark = pytest.mark.slow

HERE = os.path.dirname(__file__)
SMOKE = os.path.join(HERE, '..', 'experiments', 'smoke.py')
# Few steps, a checkpoint every 2, no pictures but the last.
FLAGS = ['--config.checkpoint_every=2', '--config.log_every=2',
         '--config.image_every=100000']
ITEMS = ('g_params', 'd_params', 'ema_params', 'g_opt', 'd_opt')
NOISE = re.compile(r'Traceback|Check failure|Fatal Python|coordination_service|^[EFW]\d{4} ',
                   re.M)


def _env(tmp_path):
  env = dict(os.environ, DUSTY_JAX_CACHE=str(tmp_path / 'cache'))
  env['XLA_FLAGS'] = FAST_COMPILE  # one CPU device per process
  env.pop('DUSTY_JAX_TRACEBACK', None)
  return env


def _free_port():
  with socket.socket() as s:
    s.bind(('127.0.0.1', 0))
    return s.getsockname()[1]


def _train(tmp_path, workdir, *flags, processes=2):
  """Starts the training command's processes; their output goes to
  ``workdir``.K.log beside the run directory."""
  port = _free_port()
  procs = []
  for k in range(processes):
    multi = (['--coordinator', f'127.0.0.1:{port}', '--num_processes', str(processes),
              '--process_id', str(k)] if processes > 1 else [])
    log = open(f'{workdir}.{k}.log', 'w')
    procs.append(subprocess.Popen(
        [sys.executable, '-m', 'dusty_jax.train', '--config', SMOKE, '--workdir',
         str(workdir), f'--config.data.cache={tmp_path / "cache"}', *FLAGS, *multi,
         *flags], env=_env(tmp_path), stdout=log, stderr=subprocess.STDOUT))
    log.close()
  return procs


def _log(workdir, k=0):
  with open(f'{workdir}.{k}.log') as f:
    return f.read()


def _messages(text):
  """The lines of a log without the progress bar's frames."""
  return [l for l in re.split(r'[\r\n]+', text)
          if l.strip() and not re.search(r'\d+%\|', l) and not l.startswith('[Gloo]')]


def _finish(procs, workdir, timeout=900):
  codes = [p.wait(timeout=timeout) for p in procs]
  assert codes == [0] * len(procs), '\n'.join(
      f'--- process {k} (exit {c}):\n{_log(workdir, k)[-3000:]}'
      for k, c in enumerate(codes))


def _wait_for(path, procs, workdir, timeout=900):
  end = time.time() + timeout
  while not os.path.exists(path):
    for k, p in enumerate(procs):
      assert p.poll() is None, f'process {k} ended early:\n{_log(workdir, k)[-3000:]}'
    assert time.time() < end, f'{path} did not appear'
    time.sleep(0.2)


def _state(workdir, step):
  directory = os.path.join(workdir, checkpoint.DIRECTORY)
  return {name: checkpoint.restore_item(directory, name, step)[0] for name in ITEMS}


def _assert_close(got, want, rtol, atol):
  import jax
  for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(got), jax.tree.leaves(want)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=atol,
                               err_msg=jax.tree_util.keystr(path))


GLOO_RESET = ('[../third_party/gloo/transport/tcp/pair.cc:538] Read error '
              '[127.0.0.1]:41353: Connection reset by peer')


def test_a_peer_lost_during_a_checkpoint_write_reads_as_a_lost_peer(monkeypatch):
  """A peer killed while a checkpoint is written fails the write with Gloo's
  lost connection, in whatever type orbax raises: that is a lost peer (the
  run says which checkpoint to resume from), not a failed write."""
  monkeypatch.setattr(parallel.jax, 'process_count', lambda: 2)
  try:
    try:
      raise RuntimeError(f'sync_global_devices failed: {GLOO_RESET}')
    except RuntimeError as e:
      raise checkpoint.CheckpointError('writing checkpoint 4 in run/checkpoints failed') from e
  except checkpoint.CheckpointError as e:
    assert any(parallel.is_peer_loss(x) for x in errors.causes(e))
  # Other errors that mention connections are not: a disk, a refused download.
  for text in ('No space left on device', 'Connection reset by peer while fetching a URL'):
    assert not parallel.is_peer_loss(RuntimeError(text))
  # UNAVAILABLE or a refused connection is a lost peer where it is the
  # coordination service's address (process 0), not another's.
  monkeypatch.setitem(parallel._run, 'coordinator', '127.0.0.1:41353')
  grpc = ('UNAVAILABLE: failed to connect to all addresses; last error: UNKNOWN: '
          'ipv4:{}: Failed to connect to remote host: Connection refused')
  assert parallel.is_peer_loss(jax.errors.JaxRuntimeError(grpc.format('127.0.0.1:41353')))
  for other in ('127.0.0.1:4135', '10.0.0.7:413530', 'storage.example.com:443'):
    try:
      try:
        raise jax.errors.JaxRuntimeError(grpc.format(other))
      except jax.errors.JaxRuntimeError as e:
        raise checkpoint.CheckpointError('writing checkpoint 4 failed') from e
    except checkpoint.CheckpointError as e:
      assert not any(parallel.is_peer_loss(x) for x in errors.causes(e)), other
  monkeypatch.setitem(parallel._run, 'coordinator', None)  # joined by other means
  assert not parallel.is_peer_loss(jax.errors.JaxRuntimeError(grpc.format('127.0.0.1:41353')))
  assert parallel.is_peer_loss(jax.errors.JaxRuntimeError(
      'UNAVAILABLE: the coordination service has stopped'))
  monkeypatch.setattr(parallel.jax, 'process_count', lambda: 1)
  assert not parallel.is_peer_loss(RuntimeError(GLOO_RESET))


def test_a_lost_process_then_a_rerun_resumes_as_if_uninterrupted(tmp_path):
  run = str(tmp_path / 'run')
  procs = _train(tmp_path, run, '--config.num_steps=100000')
  try:
    _wait_for(os.path.join(run, checkpoint.DIRECTORY, '2'), procs, run)
    procs[1].send_signal(signal.SIGKILL)
    # The survivor ends by itself (a lost peer), in the project's words.
    assert procs[0].wait(timeout=600) == 1
  finally:
    for p in procs:
      p.kill()
      p.wait()
  last = checkpoint.saved_steps(run)[-1]
  lines = _messages(_log(run))
  assert lines[-1].startswith('error: a process of this run was lost (') and lines[-1].endswith(
      f'the last checkpoint is step {last} in {run}; rerun all 2 processes to resume from '
      'it'), lines[-5:]
  assert not NOISE.search(_log(run)), _log(run)[-3000:]
  # Both processes had their lock on the run directory.
  assert {'train.lock', 'train.lock.1'} <= set(os.listdir(run))

  # Side by side: the same 2 processes again, to 2 steps beyond the
  # checkpoint; from a copy, one process with the machine's device count;
  # and an uninterrupted run of 2 processes, which ends by fitting drop
  # levels (each process inverts the training scans; one writes).
  end = last + 2
  alone, whole = str(tmp_path / 'alone'), str(tmp_path / 'whole')
  shutil.copytree(run, alone)
  levelled = {whole: ['--config.drops.depth_levels=True']}
  runs = {d: _train(tmp_path, d, f'--config.num_steps={end}', *levelled.get(d, []),
                    processes=1 if d == alone else 2)
          for d in (run, alone, whole)}
  for d, procs in runs.items():
    _finish(procs, d)
  assert all(f'resumed from step {last}' in _log(run, k) for k in (0, 1))
  assert f'resumed from step {last}' in _log(alone)

  fitted = levels.load(whole)
  assert fitted is not None and fitted[1] == end and np.isfinite(fitted[0]).all()
  assert 'drop levels written' in _log(whole, 0) and not NOISE.search(_log(whole, 1))
  want = _state(whole, end)
  _assert_close(_state(run, end), want, rtol=1e-6, atol=1e-7)
  # Another device count: the same training, to float rounding.
  _assert_close(_state(alone, end), want, rtol=1e-4, atol=1e-5)
  # metrics.jsonl holds each step once, in order, up to the end.
  steps = [json.loads(l)['step'] for l in open(os.path.join(run, 'metrics.jsonl'))]
  assert steps == sorted(set(steps)) and steps[-1] == end
  trained_on = json.load(open(os.path.join(run, 'config.json')))['trained_on']
  assert (trained_on['devices'], trained_on['processes']) == (2, 2)


def test_a_silent_process_ends_its_peer_within_peer_timeout(tmp_path):
  run = str(tmp_path / 'run')
  procs = _train(tmp_path, run, '--config.num_steps=100000', '--peer_timeout=10')
  try:
    # The watch starts before the lock files are written; data.json once the
    # data is simulated (a process ended by the watch while its simulation's
    # worker pool runs leaves the pool's semaphores to multiprocessing's
    # resource tracker, which warns after the error line).
    _wait_for(os.path.join(run, 'train.lock.1'), procs, run)
    _wait_for(os.path.join(run, 'data.json'), procs, run)
    procs[1].send_signal(signal.SIGSTOP)  # alive, but silent (a hung host)
    assert procs[0].wait(timeout=600) == 1
  finally:
    for p in procs:
      p.kill()
      p.wait()
  lines = _messages(_log(run))
  assert lines[-1].startswith(
      'error: a process of this run was lost (process 1 gave no sign of life for 10 s); '), lines
  assert re.search(r'(no checkpoint was saved yet; rerun all 2 processes to start afresh|'
                   r'the last checkpoint is step \d+ in .*; rerun all 2 processes)$',
                   lines[-1]), lines[-1]
  assert not NOISE.search(_log(run)), _log(run)[-3000:]


def test_a_second_training_on_a_held_run_directory_refuses_in_one_line(tmp_path):
  run = tmp_path / 'run'
  run.mkdir()  # (a directory the lock made, it would remove with the lock)
  with parallel.hold_workdir(str(run)):
    res = subprocess.run([sys.executable, '-m', 'dusty_jax.train', '--config', SMOKE,
                          '--workdir', str(run)], env=_env(tmp_path),
                         capture_output=True, text=True, timeout=600)
  assert res.returncode == 1, res.stderr[-3000:]
  assert _messages(res.stderr) == [
      f'error: {run} is in use by another training ({run}/train.lock is held by pid '
      f'{os.getpid()} on host {socket.gethostname()}); wait for it to end, or use '
      'another --workdir'], res.stderr[-3000:]
  assert os.listdir(run) == ['train.lock']  # nothing written


def test_a_killed_holder_leaves_nothing_to_clean(tmp_path):
  run = str(tmp_path / 'run')
  holder = subprocess.Popen(
      [sys.executable, '-c', 'import sys, time\nfrom dusty_jax import parallel\n'
       f'with parallel.hold_workdir({run!r}):\n  print("held", flush=True)\n'
       '  time.sleep(600)'], env=_env(tmp_path), stdout=subprocess.PIPE, text=True)
  try:
    assert holder.stdout.readline().strip() == 'held'
    with pytest.raises(parallel.WorkdirInUse, match=f'held by pid {holder.pid} on host'):
      with parallel.hold_workdir(run):
        pass
  finally:
    holder.kill()  # SIGKILL: no handler of ours runs
    holder.wait()
  with parallel.hold_workdir(run):  # the OS released it
    with open(os.path.join(run, parallel.LOCK_FILE)) as f:
      assert f.read() == f'pid {os.getpid()} on host {socket.gethostname()}\n'


def test_a_process_k_lock_file_goes_with_its_lock(tmp_path, monkeypatch):
  """train.lock.K of process K > 0 is removed on leaving, but only by the
  process that held it; train.lock (process 0's) stays."""
  import fcntl
  run = tmp_path / 'run'
  run.mkdir()
  monkeypatch.setattr(parallel.jax, 'process_index', lambda: 1)
  with parallel.hold_workdir(str(run)):
    assert os.listdir(run) == ['train.lock.1']
  assert os.listdir(run) == []
  # Held by another: refused, and its file is left alone.
  other = os.open(run / 'train.lock.1', os.O_RDWR | os.O_CREAT)
  try:
    fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)
    with pytest.raises(parallel.WorkdirInUse, match='train.lock.1 is held'):
      with parallel.hold_workdir(str(run)):
        pass
    assert os.listdir(run) == ['train.lock.1']
  finally:
    os.close(other)
  monkeypatch.setattr(parallel.jax, 'process_index', lambda: 0)
  with parallel.hold_workdir(str(run)):
    pass
  assert sorted(os.listdir(run)) == ['train.lock', 'train.lock.1']


# Two processes agree on texts twice (as hold_workdir and a training's log
# steps do), then process 0 lists what the coordination service still holds
# under dusty_jax/.
_AGREE = """
import sys
import jax
from dusty_jax import parallel
port, k = sys.argv[1], int(sys.argv[2])
parallel.initialize_distributed(f'127.0.0.1:{port}', 2, k)
print(parallel.all_texts('lock', f'from {k}'), parallel.all_texts('save', 'yes' if k else ''))
client = parallel._client()
client.wait_at_barrier('test/done', 300_000)
if k == 0:
  print(client.key_value_dir_get('dusty_jax/'))
client.wait_at_barrier('test/listed', 300_000)
"""


def test_agreeing_leaves_no_keys_behind(tmp_path):
  port = _free_port()
  procs = [subprocess.Popen([sys.executable, '-c', _AGREE, str(port), str(k)],
                            env=_env(tmp_path), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True) for k in (0, 1)]
  try:
    outs = [p.communicate(timeout=300) for p in procs]
  finally:
    for p in procs:
      p.kill()
  assert [p.returncode for p in procs] == [0, 0], [o[1][-2000:] for o in outs]
  lines = [o[0].splitlines() for o in outs]
  assert lines[1] == ["['from 0', 'from 1'] ['', 'yes']"]
  assert lines[0] == lines[1] + ['[]']
