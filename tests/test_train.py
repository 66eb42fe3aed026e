"""Training: data parallelism, multi-process, resume, NaN guard, CLI, API."""

import dataclasses
import json
import shutil
import os
import re
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest

import dusty_jax
from dusty_jax import after_training, checkpoint, configs, drops, levels, parallel, trainer, writers
from conftest import FAST_COMPILE
from event_files import read_events, scalars
from train_helpers import STUDY, run_steps, tiny_config

HERE = os.path.dirname(__file__)


def _assert_trees_close(a, b, rtol=1e-4, atol=1e-5):
  la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
  assert len(la) == len(lb)
  for x, y in zip(la, lb):
    np.testing.assert_allclose(x, y, rtol=rtol, atol=atol)


def assert_same_training(a, b):
  """Same parameters up to float summation order."""
  _assert_trees_close(a, b, rtol=1e-4, atol=1e-5)


@pytest.fixture(scope='module')
def one_device_params():
  assert len(jax.devices()) == 4, 'conftest forces 4 host devices'
  return run_steps(2, devices=jax.devices()[:1])


@pytest.mark.slow
def test_one_and_four_devices_agree(one_device_params):
  four = run_steps(2, devices=jax.devices())
  assert_same_training(one_device_params, four)
  # And training moved the parameters at all.
  init = run_steps(0, devices=jax.devices()[:1])
  moved = [np.abs(a - b).max() for a, b in zip(jax.tree.leaves(init['g']),
                                              jax.tree.leaves(one_device_params['g']))]
  assert max(moved) > 1e-3


@pytest.mark.slow
def test_rate_terms_are_the_global_batch_s_on_four_devices():
  # The drops terms' tallies are summed over the devices, so one and four
  # devices train the same. Each device's share of the reals drops at its
  # own rate, so per-device rates would differ from the batch's. Two steps,
  # with sim-dusty2's options (the rate term weighted up).
  config = tiny_config()
  config.drops.update(STUDY['DIPS'], rate_weight=1e3)
  configs.validate(config)
  rates = np.repeat([0.05, 0.3, 0.6, 0.9], config.batch_size // 4)
  one = run_steps(2, devices=jax.devices()[:1], config=config, drop_rates=rates)
  four = run_steps(2, devices=jax.devices(), config=config, drop_rates=rates)
  assert_same_training(one, four)


def test_rate_penalty_on_four_devices_is_the_global_batch_s():
  """The cells' counts are summed over devices: each device's pair of scans
  keeps at its own rate, so no device alone has the batch's rates."""
  from jax.sharding import PartitionSpec as P
  from dusty_jax import codec
  from dusty_jax.sensor import tiny_sensor
  sensor = tiny_sensor(16, 64)
  rng = np.random.default_rng(3)
  scans = np.asarray(codec.encode(rng.uniform(2, 100, (8, 16, 64)).astype(np.float32),
                                  sensor))
  keep = rng.uniform(size=scans.shape).astype(np.float32)
  real = (rng.uniform(size=scans.shape) < np.repeat([0.9, 0.6, 0.3, 0.1], 2)[:, None, None])
  real = (np.where(real, scans, codec.ALPHA), real.astype(np.float32))
  fake = (np.where(keep > 0.5, scans, codec.ALPHA), keep)
  alone = drops.ring_depth_rate_penalty(sensor, fake, real)
  assert float(alone) > 0
  sharded = jax.jit(jax.shard_map(
      lambda f, r: drops.ring_depth_rate_penalty(sensor, f, r, parallel.AXIS),
      mesh=parallel.data_mesh(jax.devices()), in_specs=(P(parallel.AXIS), P(parallel.AXIS)),
      out_specs=P()))
  np.testing.assert_allclose(sharded(fake, real), alone, rtol=1e-5)
  one_device = drops.ring_depth_rate_penalty(sensor, *((a[:2], b[:2]) for a, b in (fake, real)))
  assert abs(float(one_device) - float(alone)) > 1e-3


@pytest.mark.parametrize('batch, cores, want', [
    (16, 2, 4), (32, 2, 4), (8, 2, 2), (4, 2, 1), (6, 2, 1), (16, 1, 2), (32, 16, 8),
    (48, 16, 12), (24, 4, 6), (0, 2, 1)])
def test_cpu_device_count_gives_shards_of_four_or_more_two_per_core(batch, cores, want):
  assert parallel.cpu_device_count(batch, cores) == want


_USE_CORES = """
import jax
from dusty_jax import parallel
several_processes = parallel.use_cpu_cores(16, processes=2)
n = parallel.use_cpu_cores(16)
print(n, len(jax.devices()), parallel.cpu_device_count(16), parallel.use_cpu_cores(8),
      len(jax.devices()), several_processes)
"""


@pytest.mark.parametrize('env, want', [
    ({}, 'auto'),
    ({'XLA_FLAGS': '--xla_force_host_platform_device_count=3'}, 'None 3'),
    ({'JAX_NUM_CPU_DEVICES': '3'}, 'None 3')])
def test_use_cpu_cores_sets_the_count_unless_the_user_chose(env, want):
  """It sets cpu_device_count's devices before JAX's first operation, and
  leaves alone a user's own count, a run of several processes, and backends
  already up."""
  base = {k: v for k, v in os.environ.items()
          if k not in ('XLA_FLAGS', 'JAX_NUM_CPU_DEVICES')}
  res = subprocess.run([sys.executable, '-c', _USE_CORES], env=dict(base, **env),
                       capture_output=True, text=True, timeout=120)
  assert res.returncode == 0, res.stderr[-3000:]
  got = res.stdout.split()
  assert got[5] == 'None', res.stdout  # several processes: untouched
  # Once the backends are up, another count is refused and nothing changes.
  assert got[4] == got[1] and got[3] in ('None', got[1]), res.stdout
  if want == 'auto':
    assert got[0] == got[1] == got[2], res.stdout
  else:
    assert ' '.join(got[:2]) == want, res.stdout


def _run_two_processes(out):
  """Both workers' (return codes, output); a fresh free port each call."""
  with socket.socket() as s:
    s.bind(('127.0.0.1', 0))
    port = s.getsockname()[1]
  env = dict(os.environ, PYTHONPATH=os.pathsep.join(
      [os.path.join(HERE, '..'), os.environ.get('PYTHONPATH', '')]))
  env['XLA_FLAGS'] = FAST_COMPILE  # no forced count: the trainer's (use_cpu_cores)
  procs = [subprocess.Popen([sys.executable, os.path.join(HERE, 'multihost_worker.py'),
                             str(port), str(i), out], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
           for i in range(2)]
  try:
    logs = [p.communicate(timeout=1500)[0].decode(errors='replace') for p in procs]
  finally:
    for p in procs:
      p.kill()
  return [p.returncode for p in procs], logs


@pytest.mark.slow
def test_two_processes_agree_with_one(one_device_params, tmp_path):
  out = str(tmp_path / 'params.npz')
  codes, logs = _run_two_processes(out)
  if any(codes) and any('in use' in l.lower() for l in logs):
    codes, logs = _run_two_processes(out)  # the free port was taken meanwhile
  # On failure, show the end of each worker's output (where the error is).
  assert not any(codes), '\n'.join(
      f'--- worker {i} (exit {c}), last lines:\n{l[-4000:]}'
      for i, (c, l) in enumerate(zip(codes, logs)))
  got = np.load(out)
  want = jax.tree.leaves(one_device_params)
  assert len(got.files) == len(want)
  assert_same_training([got[f'arr_{i}'] for i in range(len(want))], want)


@pytest.mark.slow
def test_resume_is_exact(smoke_run, tmp_path):
  config, workdir, final = smoke_run
  # A run stopped at step 2 and resumed reaches step 4 with the same params;
  # the tmp folder of a step-4 save cut short (a kill) is cleared first.
  config = config.copy_and_resolve_references()
  config.num_steps = 2
  other = str(tmp_path / 'resumed')
  trainer.train_and_evaluate(config, other, log=lambda m: None)
  os.makedirs(os.path.join(other, 'checkpoints', '4.orbax-checkpoint-tmp-1'))
  config.num_steps = 4
  logs = []
  resumed = trainer.train_and_evaluate(config, other, log=logs.append)
  assert any('resumed from step 2' in l for l in logs)
  _assert_trees_close(parallel.to_host(resumed), final, rtol=1e-6, atol=1e-7)
  assert sorted(os.listdir(os.path.join(other, 'checkpoints'))) == ['2', '4']


def test_run_outputs(smoke_run):
  config, workdir, _ = smoke_run
  assert sorted(os.listdir(os.path.join(workdir, 'checkpoints'))) == ['2', '4']
  labels = writers.read_labels(os.path.join(workdir, 'images', 'step_0000004.png'))
  assert labels['panels'][:3] == ['sample scan (sample 1)', 'complete depth x_tilde (sample 1)',
                                  'measurability (sample 1)']
  assert len(labels['colour bars']) == 3
  lines = [json.loads(l) for l in open(os.path.join(workdir, 'metrics.jsonl'))]
  assert [l['step'] for l in lines] == [1, 2, 4]  # the first step, then log_every
  assert all(np.isfinite(l['loss_d']) and l['images_per_sec'] > 0 for l in lines)
  # The devices it trained on (the test session's 4 CPU devices).
  assert json.load(open(os.path.join(workdir, 'config.json')))['trained_on'] == {
      'devices': jax.device_count(), 'processes': 1, 'platform': 'cpu'}
  events = [f for f in os.listdir(workdir) if f.startswith('events.out.tfevents')]
  records = read_events(os.path.join(workdir, events[0]))
  assert records[0].file_version == 'brain.Event:2'
  logged = scalars(records)
  for l in lines:  # every JSONL scalar is in the event file at its step
    expected = {(l['step'], k, float(np.float32(v))) for k, v in l.items()
                if k not in ('step', 'time')}
    assert expected <= set(logged)


@pytest.mark.slow
def test_checkpoints_by_wall_time(smoke_run, tmp_path):
  """checkpoint_minutes saves when that long has passed since the last save,
  whatever checkpoint_every says (a tiny value: every step); smoke_run's
  default of 10 minutes saved by steps only."""
  config = smoke_run[0].copy_and_resolve_references()
  config.update(num_steps=3, checkpoint_every=1000, checkpoint_minutes=1e-9,
                keep_checkpoints=5, image_every=1000)
  trainer.train_and_evaluate(config, str(tmp_path / 'w'), log=lambda m: None)
  assert sorted(os.listdir(tmp_path / 'w' / 'checkpoints'), key=int) == ['1', '2', '3']


@pytest.mark.parametrize('minutes', [-1.0, float('nan'), float('inf')])
def test_checkpoint_minutes_is_checked(minutes):
  config = tiny_config()
  config.checkpoint_minutes = minutes
  with pytest.raises(configs.ConfigError, match='checkpoint_minutes'):
    configs.validate(config)


def test_load_checkpoint_and_sample(smoke_run):
  config, workdir, final = smoke_run
  params, cfg = dusty_jax.load_checkpoint(workdir)
  assert cfg.model == 'dusty1' and params.sensor.shape == (16, 64)
  _assert_trees_close(params.variables, final.ema_params, rtol=0, atol=0)
  out = dusty_jax.sample(params, jax.random.key(0), 3)
  assert out['scan'].shape == out['inv_depth'].shape == (3, 16, 64)
  assert out['points'].shape == (3, 16, 64, 3)
  m = np.asarray(out['mask'])
  assert set(np.unique(m).tolist()) <= {0.0, 1.0}
  np.testing.assert_array_equal(np.asarray(out['scan'])[m == 0], -1.0)
  np.testing.assert_allclose(np.asarray(out['scan'])[m == 1],
                             np.asarray(out['inv_depth'])[m == 1])
  depth = np.linalg.norm(np.asarray(out['points']), axis=-1)
  np.testing.assert_allclose(depth, np.asarray(out['depth']), rtol=1e-5, atol=1e-5)
  again = dusty_jax.sample(params, jax.random.key(0), 3)
  np.testing.assert_array_equal(out['scan'], again['scan'])


@pytest.mark.slow
def test_nan_stops_training_keeping_last_good_checkpoint(smoke_run, tmp_path):
  config, workdir, _ = smoke_run
  config = config.copy_and_resolve_references()
  other = str(tmp_path / 'nan')
  config.num_steps = 2
  trainer.train_and_evaluate(config, other, log=lambda m: None)
  config.num_steps = 6
  config.lr = 1e38  # from step 3 on, updates overflow float32: inf, then NaN.
  with pytest.raises(trainer.NonFiniteLossError, match=(
      r'non-finite training metrics at step \d+: .*the last checkpoint, step 2, is '
      'kept and a rerun resumes from it')):
    trainer.train_and_evaluate(config, other, log=lambda m: None)
  assert sorted(os.listdir(os.path.join(other, 'checkpoints'))) == ['2']


@pytest.mark.slow
def test_keep_every_keeps_the_multiples_beside_the_last(smoke_run, tmp_path):
  config, _, _ = smoke_run
  config = config.copy_and_resolve_references()
  config.num_steps, config.checkpoint_every = 7, 1
  config.keep_checkpoints, config.keep_every = 2, 3
  trainer.train_and_evaluate(config, str(tmp_path / 'w'), log=lambda m: None)
  assert sorted(int(s) for s in os.listdir(tmp_path / 'w' / 'checkpoints')) == [3, 6, 7]


def test_missing_dataset_message(tmp_path):
  config = tiny_config()
  config.data.dir = str(tmp_path / 'nothing')
  config.data.name = 'kitti'
  with pytest.raises(FileNotFoundError, match=r'dusty_jax\.tools\.prepare.*synthetic\.py'):
    trainer.train_and_evaluate(config, str(tmp_path / 'w'), log=lambda m: None)


@pytest.mark.slow
def test_cli_trains_with_overrides(tmp_path):
  """The command line trains with --config.FIELD overrides (its bad fields
  and missing data: test_cli.py's table)."""
  env = dict(os.environ, DUSTY_JAX_CACHE=str(tmp_path / 'cache'))
  env['XLA_FLAGS'] = FAST_COMPILE  # no forced count: the trainer's (use_cpu_cores)
  cmd = [sys.executable, '-m', 'dusty_jax.train',
         '--config', os.path.join(HERE, '..', 'experiments', 'smoke.py'),
         '--workdir', str(tmp_path / 'w')]
  ok = subprocess.run(cmd + ['--config.num_steps=2', '--config.log_every=1',
                             '--config.data.num_synthetic=8'],
                      env=env, capture_output=True, text=True, timeout=600)
  assert ok.returncode == 0, ok.stderr[-3000:]
  assert os.path.isdir(tmp_path / 'w' / 'checkpoints' / '2')
  assert json.load(open(tmp_path / 'w' / 'config.json'))['num_steps'] == 2


@pytest.mark.slow
def test_ema_rampup_follows_generator_early():
  """With the ramp-up, after one step of 8 images the half-life is 0.4
  images: the EMA equals the generator; without it, it stays near the init."""
  with_rampup = run_steps(1, devices=jax.devices()[:1],
                          config=tiny_config(ema_rampup=0.05))
  _assert_trees_close(with_rampup['ema'], with_rampup['g'], rtol=1e-5, atol=1e-6)
  plain = run_steps(1, devices=jax.devices()[:1])
  g, e = (np.concatenate([np.ravel(v) for v in jax.tree.leaves(plain[k])])
          for k in ('g', 'ema'))
  assert np.abs(g - e).max() > 1e-3


@pytest.mark.parametrize('field,value', [
    ('batch_size', 0), ('checkpoint_every', 0), ('log_every', 0), ('lr', -0.002),
    ('num_steps', 0), ('keep_checkpoints', 0), ('keep_every', -1), ('r1_every', 0),
    ('tau', 0.0), ('augment', 'brightness,zoom'), ('augment_style', 'fancy'),
    ('after_training', 'levels,plots')])
def test_config_is_checked_before_any_work(tmp_path, field, value):
  config = tiny_config(**{field: value})
  workdir = tmp_path / 'w'
  with pytest.raises(configs.ConfigError, match=field):
    trainer.train_and_evaluate(config, str(workdir), log=lambda m: None)
  assert not workdir.exists()


def test_resume_with_another_architecture_is_refused_untouched(smoke_run, tmp_path):
  config, workdir, _ = smoke_run
  copy = tmp_path / 'copy'
  shutil.copytree(workdir, copy)
  before = (copy / 'config.json').read_bytes()
  other = tiny_config(ch_base=4, num_steps=6)
  other.data.cache = config.data.cache
  other.data.num_synthetic = config.data.num_synthetic
  with pytest.raises(configs.ConfigError, match=r'ch_base: run has 8, config has 4'):
    trainer.train_and_evaluate(other, str(copy), log=lambda m: None)
  assert (copy / 'config.json').read_bytes() == before


def test_cli_config_error_is_one_line(tmp_path):
  env = dict(os.environ, DUSTY_JAX_CACHE=str(tmp_path / 'cache'))
  env['XLA_FLAGS'] = FAST_COMPILE  # no forced count: the trainer's (use_cpu_cores)
  res = subprocess.run([sys.executable, '-m', 'dusty_jax.train', '--config',
                        os.path.join(HERE, '..', 'experiments', 'smoke.py'),
                        '--workdir', str(tmp_path / 'w'), '--config.batch_size=0'],
                       env=env, capture_output=True, text=True, timeout=300)
  assert res.returncode != 0 and 'Traceback' not in res.stderr
  assert 'batch_size=0' in res.stderr.strip().splitlines()[-1]
  assert not (tmp_path / 'w').exists()


@pytest.mark.slow
@pytest.mark.parametrize('damage', ['truncate', 'metadata', 'empty'])
def test_damaged_latest_checkpoint_falls_back(smoke_run, tmp_path, damage):
  config, workdir, _ = smoke_run
  copy = tmp_path / 'copy'
  _damaged_copy(workdir, copy, damage)
  messages = []
  params, _ = dusty_jax.load_checkpoint(str(copy))  # falls back to step 2
  ref, _ = dusty_jax.load_checkpoint(str(workdir), step=2)
  for a, b in zip(jax.tree.leaves(params.variables), jax.tree.leaves(ref.variables)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  with pytest.raises(FileNotFoundError, match=r'saved steps: \[2, 4\]'):
    dusty_jax.load_checkpoint(str(workdir), step=3)
  if damage != 'empty':
    return
  # Resume trains on from step 2 and can save step 4 again.
  trainer.train_and_evaluate(config, str(copy), log=messages.append)
  assert any('step 4' in m and 'does not restore' in m for m in messages)
  assert any('resumed from step 2' in m for m in messages)
  assert dusty_jax.load_checkpoint(str(copy))[0] is not None


def _damaged_copy(workdir, dest, damage):
  shutil.copytree(workdir, dest)
  latest = dest / 'checkpoints' / '4'
  if damage == 'empty':
    shutil.rmtree(latest)
    latest.mkdir()
  elif damage == 'metadata':
    (latest / '_CHECKPOINT_METADATA').unlink()
    for p in latest.rglob('_METADATA'):
      p.unlink()
  else:  # every array data file cut to 30%: many reads fail at once.
    for p in latest.rglob('*'):
      if p.is_file() and p.parent.name == 'd' and p.stat().st_size > 512:
        p.write_bytes(p.read_bytes()[:int(p.stat().st_size * 0.3)])
  return dest


LOAD_AND_RESUME = '''
import sys
import jax
import dusty_jax
from dusty_jax import checkpoint, configs, sensor, trainer
for name in sys.argv[1:]:
  print('--- load ' + name, file=sys.stderr, flush=True)
  dusty_jax.load_checkpoint(name)
  print('--- resume ' + name, file=sys.stderr, flush=True)
  config = configs.load(name)
  setup = trainer.make_setup(config, sensor.from_config(config.sensor))
  state = trainer.init_state(setup, jax.random.key(0))
  checkpoint.restore_latest(checkpoint.manager(name), state)
print('--- end', file=sys.stderr, flush=True)
'''


@pytest.mark.slow
def test_damaged_checkpoints_are_one_line_each_and_loads_are_silent(smoke_run, tmp_path):
  """Per skipped step one warning with a reason a person can
  act on, then the step loaded, and nothing else on stderr (no asyncio or
  TensorStore noise such as 'Event loop is closed', no orbax warning per
  load); an intact run loads in silence. The truncated step is found by its
  manifest, which names a file."""
  _, workdir, _ = smoke_run
  runs = [str(workdir)] + [str(_damaged_copy(workdir, tmp_path / d, d))
                           for d in ('truncate', 'metadata', 'empty')]
  env = dict(os.environ)
  env['XLA_FLAGS'] = FAST_COMPILE  # no forced count: the trainer's (use_cpu_cores)
  res = subprocess.run([sys.executable, '-c', LOAD_AND_RESUME] + runs, env=env,
                       capture_output=True, text=True, timeout=600,
                       cwd=os.path.join(HERE, '..'))
  assert res.returncode == 0, res.stderr[-3000:]
  blocks, name = {}, None
  for line in res.stderr.splitlines():
    if line.startswith('--- '):
      name = line[4:]
      blocks[name] = []
    else:
      blocks[name].append(line)
  assert blocks.pop('end') == []
  assert blocks.pop(f'load {runs[0]}') == [] and blocks.pop(f'resume {runs[0]}') == []
  assert 'Event loop is closed' not in res.stderr and 'Traceback' not in res.stderr
  reasons = {'truncate': r'file truncated: default/\S*d/[0-9a-f]+ has \d+ bytes, '
                         r'\d+ when saved, and \d+ more files',
             'metadata': r'file missing: _CHECKPOINT_METADATA, and \d+ more files',
             'empty': 'empty directory'}
  for run, damage in zip(runs[1:], ('truncate', 'metadata', 'empty')):
    d = os.path.join(run, 'checkpoints')
    want = (rf'warning: checkpoint step 4 in {re.escape(d)} does not restore '
            rf'\({reasons[damage]}\); trying the previous one\n'
            rf'loaded checkpoint step 2 from {re.escape(d)}')
    for what in ('load', 'resume'):
      assert re.fullmatch(want, '\n'.join(blocks[f'{what} {run}'])), res.stderr[-3000:]


def test_a_step_unlike_its_manifest_is_not_read(smoke_run, tmp_path, monkeypatch):
  """A step whose files differ in size from those saved is skipped before
  orbax reads it (a failed read leaves TensorStore reads printing 'Event
  loop is closed'), with the file that differs."""
  _, workdir, _ = smoke_run
  copy = _damaged_copy(workdir, tmp_path / 'copy', 'truncate')
  read = []
  restore = checkpoint.ocp.CheckpointManager.restore
  monkeypatch.setattr(checkpoint.ocp.CheckpointManager, 'restore',
                      lambda self, step, **kw: read.append(step) or restore(self, step, **kw))
  messages = []
  _, step = checkpoint.restore_item(str(copy / 'checkpoints'), 'ema_params',
                                    log=messages.append)
  assert (step, read) == (2, [2]) and 'file truncated: default/' in messages[0]


def test_a_save_without_room_is_refused_before_orbax_writes(tmp_path, monkeypatch):
  """A disk with less free space than a step needs gives the one-line error
  of a full disk before orbax writes anything (a save that fails half-way
  leaves TensorStore printing 'Event loop is closed')."""
  state = {'w': np.ones((64, 64), np.float32)}
  mngr = checkpoint.manager(str(tmp_path / 'run'))
  checkpoint.save(mngr, 1, state)
  checkpoint.wait(mngr)
  folder = tmp_path / 'run' / 'checkpoints'
  need = sum(p.stat().st_blocks * 512 for p in (folder / '1').rglob('*') if p.is_file())
  usage = shutil.disk_usage(folder)
  monkeypatch.setattr(shutil, 'disk_usage', lambda path: usage._replace(free=need))
  with pytest.raises(checkpoint.CheckpointError, match=(
      rf'^no space left on device while writing checkpoint 2 in {re.escape(str(folder))}; '
      r'step 1 is intact; free space and rerun to resume from 1$')):
    checkpoint.save(mngr, 2, state)
  assert sorted(os.listdir(folder)) == ['1']
  monkeypatch.setattr(shutil, 'disk_usage', lambda path: usage._replace(free=2 * need))
  assert checkpoint.save(mngr, 2, state)
  checkpoint.wait(mngr)
  assert checkpoint.saved_steps(str(tmp_path / 'run')) == [1, 2]


@pytest.mark.slow
def test_nan_before_any_checkpoint_says_a_rerun_starts_afresh(smoke_run, tmp_path):
  """No checkpoint exists yet, so none is 'kept'."""
  config, _, _ = smoke_run
  config = config.copy_and_resolve_references()
  config.num_steps, config.checkpoint_every, config.log_every = 6, 5, 1
  config.lr = 1e38
  with pytest.raises(trainer.NonFiniteLossError,
                     match=r'no checkpoint was saved yet, so a rerun starts afresh'):
    trainer.train_and_evaluate(config, str(tmp_path / 'w'), log=lambda m: None)
  assert not os.listdir(tmp_path / 'w' / 'checkpoints')


def test_a_run_file_given_for_a_checkpoint_names_its_directory(smoke_run):
  """config.json is not 'not a torch.save checkpoint'."""
  _, workdir, _ = smoke_run
  for name, what in (('config.json', 'config'), ('generator.json', 'generator description')):
    with pytest.raises(ValueError, match=(
        rf"{name}: a training run's {what} file, not a checkpoint; pass its "
        rf'directory, {re.escape(os.path.abspath(workdir))}')):
      dusty_jax.load_checkpoint(os.path.join(workdir, name))


def test_what_is_no_model_says_so(tmp_path):
  """A folder with another program's config.json, an .npz that export did
  not write and a scan file: each named, with what a model is."""
  (tmp_path / 'run').mkdir()
  (tmp_path / 'run' / 'config.json').write_text('{"model_type": "bert"}')
  np.savez(tmp_path / 'levels.npz', offsets=np.zeros(3))
  np.save(tmp_path / 'scan.npy', np.ones((4, 8), np.float32))
  forms = "a model is a run directory, a shipped model's name, an exported .npz"
  for path, says in [('run', r"config\.json: not a dusty_jax run config \(no 'model' field\), "
                              r'so \S+/run is no training run of this library'),
                     ('levels.npz', rf'levels\.npz: not a generator exported by dusty_jax .*; {forms}'),
                     ('scan.npy', rf'scan\.npy: not a model file \(.*\); {forms}')]:
    with pytest.raises(ValueError, match=says):
      dusty_jax.load_checkpoint(str(tmp_path / path))


def test_a_training_ends_with_its_short_evaluation(smoke_run):
  """config.final_eval: the run directory gets final_evaluation.json and
  .png, and the lines printed name the figures of that record."""
  from dusty_jax import evaluation
  _, workdir, _ = smoke_run
  record = json.load(open(os.path.join(workdir, 'final_evaluation.json')))
  # Its picture: titled panels of target, reconstruction, measurability and
  # the simulator's return probability per scan, colour bars in units.
  labels = writers.read_labels(os.path.join(workdir, 'final_evaluation.png'))
  assert labels['panels'][:4] == [f'{t} (test scan 1)' for t in (
      'target scan', 'reconstruction x_tilde', 'measurability', 'true return probability')]
  assert labels['colour bars'][0] == writers.COLOUR_BAR[writers.DEPTH]
  assert all('probability' in l for l in labels['colour bars'][2:])
  assert record['synthesis']['num'] == 4 and record['restoration']['num'] == 2
  assert record['ground_truth']['ring_table']['ece'] >= 0
  text = evaluation.summary(record)
  assert f'MMD x1e3 {1e3 * record["synthesis"]["mmd"]:.1f}' in text
  assert f'ECE {record["ground_truth"]["placement"]["ece"]:.4f}' in text
  assert "keep rate per ring" in text


@pytest.mark.slow
def test_the_steps_after_training_run_as_the_config_lists_them(smoke_run, tmp_path,
                                                               monkeypatch):
  """config.after_training names the steps after the last one, in order,
  each given the run the step before returned; a step left out does not
  run. (A finished run started again trains no step.)"""
  config, workdir, _ = smoke_run
  copy = str(tmp_path / 'copy')
  shutil.copytree(workdir, copy)
  os.remove(os.path.join(copy, 'final_evaluation.json'))
  seen = []

  def step(name):
    def run(trained):
      seen.append((name, trained.step, trained.data_dir))
      return dataclasses.replace(trained, step=trained.step + 1)
    return run

  for name in after_training.STEPS:
    monkeypatch.setitem(after_training.STEPS, name, step(name))
  config = config.copy_and_resolve_references()
  config.after_training = 'final_evaluation,levels'
  trainer.train_and_evaluate(config, copy, log=lambda m: None)
  data = seen[0][2]
  assert os.path.isdir(data)
  assert seen == [('final_evaluation', config.num_steps, data),
                  ('levels', config.num_steps + 1, data)]
  monkeypatch.undo()
  config.after_training = 'levels'  # drops.depth_levels is off: nothing to fit
  trainer.train_and_evaluate(config, copy, log=lambda m: None)
  assert not os.path.exists(os.path.join(copy, 'final_evaluation.json'))
  assert not os.path.exists(os.path.join(copy, levels.FILE))
  config.after_training = 'final_evaluation'
  said = []
  trainer.train_and_evaluate(config, copy, log=said.append)
  assert os.path.isfile(os.path.join(copy, 'final_evaluation.json'))
  assert said[-2] == 'short evaluation on the test split (config final_eval)'
