"""The data a training reads: what it is (identity.py), how it is
read (into memory, or FileRows), bad values refused before training, and a
split that changes under a run or between its launches: one line, nothing
trained on the changed bytes, the last good checkpoint kept."""

import json
import os
import re
import time

import numpy as np
import pytest

from conftest import random_depth, sensor_order_points
from dusty_jax import configs, trainer
from dusty_jax.data import arrays, identity, pipeline, prepare
from dusty_jax.data import kitti as kitti_io
from dusty_jax.errors import DataError
from test_cli import _messages, _training
from train_helpers import tiny_config

SCANS = 40


def _prepared(directory, sensor, n=SCANS, seed=0):
  """A prepared dataset of ``n`` random scans: (train.npy's path, the array)."""
  os.makedirs(directory, exist_ok=True)
  depth = np.stack([random_depth(sensor, seed=seed * 1000 + i) for i in range(n)])
  path = arrays.split_path(str(directory), 'train')
  np.save(path, depth)
  return path, depth


def _config(data_dir, **overrides):
  c = tiny_config(num_steps=4, checkpoint_every=2, log_every=2, image_every=1000)
  c.data.dir = str(data_dir)
  c.update(overrides)
  return c


def _at_step(monkeypatch, step, action):
  """Runs ``action()`` once, before the batch of ``step`` (1-based) is drawn."""
  draw = pipeline.Batches.__call__
  def patched(self, i):
    if i + 1 == step:
      action()
    return draw(self, i)
  monkeypatch.setattr(pipeline.Batches, '__call__', patched)


def _saved(workdir):
  return sorted(int(s) for s in os.listdir(os.path.join(workdir, 'checkpoints')) if s.isdigit())


# ----------------------------------------------------------------------------
# Reading: sizes, memory or file rows.
# ----------------------------------------------------------------------------


def test_a_file_cut_short_is_one_error_naming_both_sizes(tmp_path, tiny):
  path, _ = _prepared(tmp_path, tiny)
  size = os.path.getsize(path)
  with open(path, 'r+b') as f:
    f.truncate(size // 2)
  want = (rf'{re.escape(path)}: {size // 2:,} bytes where the \(40, 16, 64\) float32 of '
          rf'its header needs {size:,}: the file was cut short')
  # The mapped reader of the tools, and training's: the same line, no mmap error.
  for read in (arrays.load_split, arrays.read_split):
    with pytest.raises(DataError, match=want):
      read(str(tmp_path), 'train', tiny)


def test_a_file_that_is_no_npy_is_named(tmp_path, tiny):
  path = arrays.split_path(str(tmp_path), 'train')
  with open(path, 'wb') as f:
    f.write(b'not an array at all')
  with pytest.raises(DataError, match=rf'{re.escape(path)}: not a \.npy array'):
    arrays.read_split(str(tmp_path), 'train', tiny)


def test_file_rows_serve_what_the_array_holds(tmp_path, tiny):
  path, depth = _prepared(tmp_path, tiny)
  in_memory = arrays.read_split(str(tmp_path), 'train', tiny)
  rows = arrays.read_split(str(tmp_path), 'train', tiny, memory_bytes=0)
  assert isinstance(in_memory, np.ndarray) and isinstance(rows, arrays.FileRows)
  np.testing.assert_array_equal(in_memory, depth)
  assert len(rows) == SCANS and rows.shape == depth.shape and rows.dtype == depth.dtype
  idx = np.array([0, 3, 3, 4, 5, 17, 39])  # runs, repeats and the last row
  np.testing.assert_array_equal(rows[idx], depth[idx])
  np.testing.assert_array_equal(rows[:7], depth[:7])
  np.testing.assert_array_equal(rows[-1], depth[-1])
  with pytest.raises(IndexError, match='row 40 out of range for 40 scans'):
    rows[np.array([2, 40])]
  # A file replaced by another (a rename, as prepare writes): the old one is read.
  arrays.save_array(path, depth + 1)
  np.testing.assert_array_equal(rows[idx], depth[idx])


def test_a_file_cut_short_under_file_rows_is_an_error_naming_it(tmp_path, tiny):
  path, depth = _prepared(tmp_path, tiny)
  rows = arrays.read_split(str(tmp_path), 'train', tiny, memory_bytes=0)
  size = os.path.getsize(path)
  with open(path, 'r+b') as f:  # in place: the descriptor sees it
    f.truncate(size // 2)
  np.testing.assert_array_equal(rows[:5], depth[:5])  # what is still there
  with pytest.raises(DataError, match=rf'{re.escape(path)}: cut short while training reads '
                                      rf'it: {size // 2:,} bytes where .* needs {size:,}'):
    rows[np.array([1, 30])]


# ----------------------------------------------------------------------------
# Values: refused before training in one line with the share found.
# ----------------------------------------------------------------------------


BAD_VALUES = [
    ('all NaN', lambda d: np.full_like(d, np.nan),
     r'100\.0% of its pixels are NaN or inf; at most 1% count as drops: write 0 where'),
    ('all drops', np.zeros_like,
     r'100\.0% of its pixels are drops \(0, NaN or out of range'),
    ('millimetres', lambda d: d * 1000,
     r"only 0\.0% of its pixels lie inside the sensor's range \(0\.9, 120\) m; its "
     r"returns' median is [\d.e+]+: depths must be in metres"),
    ('NaN above the share', lambda d: np.where(np.arange(d.size).reshape(d.shape) % 20 == 0,
                                               np.nan, d),
     r'5\.0% of its pixels are NaN or inf'),
]


@pytest.mark.parametrize('name, make, says', BAD_VALUES, ids=[b[0] for b in BAD_VALUES])
@pytest.mark.parametrize('memory', [True, False], ids=['in_memory', 'file_rows'])
def test_bad_values_are_refused_with_the_share_found(tmp_path, tiny, name, make, says, memory):
  path, depth = _prepared(tmp_path, tiny)
  np.save(path, make(depth).astype(np.float32))
  data = arrays.read_split(str(tmp_path), 'train', tiny, memory_bytes=1 << 40 if memory else 0)
  with pytest.raises(DataError, match=re.escape(path) + ': ' + says):
    arrays.check_values(data, tiny, path, log=lambda m: None)


def test_a_few_nan_are_drops_and_counted(tmp_path, tiny):
  path, depth = _prepared(tmp_path, tiny)
  depth[3, 2, :10] = np.nan
  depth[7, 0, 0] = np.inf
  logs = []
  shares = arrays.check_values(depth, tiny, path, log=logs.append)
  assert logs == [f'{path}: 11 NaN or inf pixels (0.027%) taken as drops']
  assert shares['nonfinite'] == 11 / depth.size
  assert shares['valid'] == np.mean((depth > tiny.min_depth) & (depth < tiny.max_depth))


def test_a_split_too_big_for_memory_is_checked_on_scans_spread_over_it(tmp_path, tiny,
                                                                        monkeypatch):
  path, depth = _prepared(tmp_path, tiny)
  depth[:, :8] = np.nan  # half the rings of every scan: half the pixels of any sample
  np.save(path, depth)
  monkeypatch.setattr(arrays, 'CHECK_SCANS', 8)
  rows = arrays.read_split(str(tmp_path), 'train', tiny, memory_bytes=0)
  with pytest.raises(DataError, match=(re.escape(path) + r': 50\.0% of its pixels are NaN or '
                                       r'inf \(in 8 of its 40 scans, spread over it\); at most 1%')):
    arrays.check_values(rows, tiny, path, log=lambda m: None)


def test_memory_mb_is_checked():
  config = tiny_config()
  config.data.memory_mb = -1  # (a float is refused by the field's type on assignment)
  with pytest.raises(configs.ConfigError, match=r'data\.memory_mb=-1: must be a whole number'):
    configs.validate(config)


def test_a_bad_split_is_refused_before_training_writes_anything(tmp_path, tiny):
  path, depth = _prepared(tmp_path / 'data', tiny)
  np.save(path, np.full_like(depth, np.nan))
  workdir = tmp_path / 'w'
  with pytest.raises(DataError, match=r'100\.0% of its pixels are NaN'):
    trainer.train_and_evaluate(_config(tmp_path / 'data'), str(workdir), log=lambda m: None)
  assert not (workdir / 'checkpoints').exists() and not (workdir / 'config.json').exists()


# ----------------------------------------------------------------------------
# Identity: what prepare and the simulator record, what a change is.
# ----------------------------------------------------------------------------


def test_identity_tells_a_change_from_a_touch(tmp_path, tiny):
  path, depth = _prepared(tmp_path, tiny)
  first = identity.of_file(path, whole=True)
  assert first['sha256'] == identity.of_file(path, whole=True, data=depth)['sha256']
  assert first['bytes'] == os.path.getsize(path) and first['shape'] == [SCANS, 16, 64]
  os.utime(path, ns=(time.time_ns(), time.time_ns() + 10**9))  # a touch
  touched = identity.of_file(path, whole=True)
  assert touched['mtime_ns'] != first['mtime_ns'] and identity.differences(first, touched) == []
  other = depth.copy()
  other[20, 5, 5] += 1.0  # one pixel, inside the sample (the whole file: it is small)
  np.save(path, other)
  for whole in (True, False):
    changes = identity.differences(first, identity.of_file(path, whole=whole))
    assert changes[0].startswith('same size, other contents'), changes
  np.save(path, np.zeros((SCANS, 32, 64), np.float32))
  changes = identity.differences(first, identity.of_file(path))
  assert changes[:2] == [f"size {first['bytes']:,} -> {os.path.getsize(path):,} bytes",
                         'shape (40, 16, 64) -> (40, 32, 64)']


def test_the_simulator_records_its_files_and_a_damaged_cache_is_simulated_again(tmp_path,
                                                                              tiny):
  config = tiny_config()
  config.data.cache, config.data.num_synthetic = str(tmp_path), 8
  logs = []
  directory = pipeline.dataset_dir(config, tiny, log=logs.append)
  path = arrays.split_path(directory, 'train')
  recorded = arrays.read_meta(directory)['identity']
  assert sorted(recorded) == ['test', 'train', 'val']
  assert recorded['train'] == identity.of_file(path, whole=True)
  good = np.load(path)
  with open(path, 'r+b') as f:  # damaged in place
    f.truncate(os.path.getsize(path) - 100)
  logs.clear()
  assert pipeline.dataset_dir(config, tiny, log=logs.append) == directory
  assert any(re.search(r'is not what was simulated \(train\.npy: size [\d,]+ -> [\d,]+ bytes'
                       r', modified [^)]*\); simulating it again', l) for l in logs), logs
  np.testing.assert_array_equal(np.load(path), good)  # the same scans again
  logs.clear()
  pipeline.dataset_dir(config, tiny, log=logs.append)
  assert not logs  # intact now: used as it is


def test_prepare_records_each_split_it_leaves(tmp_path, kitti):
  root = tmp_path / 'kitti'
  for seq, n in (('00', 2), ('08', 1)):
    velodyne = root / 'sequences' / seq / 'velodyne'
    velodyne.mkdir(parents=True)
    for i in range(n):
      kitti_io.write_bin(str(velodyne / f'{i:06d}.bin'),
                         sensor_order_points(random_depth(kitti, seed=i), kitti))
  out = str(tmp_path / 'out')
  meta = prepare.prepare('kitti', str(root), out, log=lambda m: None)
  assert sorted(meta['identity']) == ['train', 'val']  # no test scan, no test.npy
  for split, ident in meta['identity'].items():
    assert ident == identity.of_file(arrays.split_path(out, split), whole=True)
    assert ident['shape'] == [meta['splits'][split], 64, 256]


# ----------------------------------------------------------------------------
# A training whose data changes: during the run, and between launches.
# ----------------------------------------------------------------------------


@pytest.mark.slow
def test_a_split_changed_in_place_mid_run_stops_before_the_next_checkpoint(
    tmp_path, tiny, monkeypatch):
  """The issue's first row: np.save of another shape to the same path while
  training runs. Then: the next launch is refused; with the data restored it
  resumes from the last checkpoint trained on it, after removing the folder
  of a save that a crash cut short."""
  data_dir, workdir = tmp_path / 'data', str(tmp_path / 'w')
  path, depth = _prepared(data_dir, tiny)
  other = np.ones((SCANS, 32, 64), np.float32)
  _at_step(monkeypatch, 3, lambda: np.save(path, other))
  logs = []
  config = _config(data_dir)  # 4 steps: the change is seen at the last, which saves
  with pytest.raises(DataError) as e:
    trainer.train_and_evaluate(config, workdir, log=logs.append)
  line = str(e.value)
  assert '\n' not in line
  assert re.fullmatch(
      rf'{re.escape(path)} changed during training \(size [\d,]+ -> [\d,]+ bytes, shape '
      r'\(40, 16, 64\) -> \(40, 32, 64\), modified [\d: -]+\); stopped at step 4, before '
      r'saving; the last checkpoint, step 2, was trained on the old data\. Restore the data '
      r'and rerun to resume, or rerun with --config\.data\.allow_changed=true to go on '
      r'training on the new data', line), line
  assert _saved(workdir) == [2]
  assert any(l.endswith('40 training scans, 0.2 MiB, read into memory') for l in logs), logs
  monkeypatch.undo()
  with pytest.raises(DataError, match=r'array of shape \(40, 32, 64\) does not match'):
    trainer.train_and_evaluate(config, workdir, log=lambda m: None)
  np.save(path, depth)  # put back: the same bytes, a new file time
  cut = os.path.join(workdir, 'checkpoints', '4.orbax-checkpoint-tmp')
  os.makedirs(os.path.join(cut, 'state'))
  logs = []
  trainer.train_and_evaluate(config, workdir, log=logs.append)
  assert 'resumed from step 2 in ' + workdir in logs
  assert (f'removed 1 unfinished checkpoint folder in {os.path.dirname(cut)} (a save cut '
          "short by an earlier run's end): 4.orbax-checkpoint-tmp") in logs
  assert _saved(workdir) == [2, 4] and not os.path.exists(cut)


@pytest.mark.slow
def test_a_split_truncated_mid_run_stops_in_one_line(tmp_path, tiny, monkeypatch):
  """The default reading (into memory) trains on what it read; the file cut
  short is seen at the next log step, and a rerun names both sizes."""
  data_dir, workdir = tmp_path / 'data', str(tmp_path / 'w')
  path, _ = _prepared(data_dir, tiny)
  size = os.path.getsize(path)
  def truncate():
    with open(path, 'r+b') as f:
      f.truncate(size // 2)
  _at_step(monkeypatch, 3, truncate)
  with pytest.raises(DataError, match=(
      rf'^{re.escape(path)} changed during training \(size {size:,} -> {size // 2:,} bytes'
      r'[^\n]*stopped at step 4, before saving; the last checkpoint, step 2, ')):
    trainer.train_and_evaluate(_config(data_dir), workdir, log=lambda m: None)
  assert _saved(workdir) == [2]
  assert not [n for n in os.listdir(os.path.join(workdir, 'checkpoints')) if 'tmp' in n]
  with pytest.raises(DataError, match=rf'{size // 2:,} bytes where .* needs {size:,}'):
    trainer.train_and_evaluate(_config(data_dir), workdir, log=lambda m: None)


@pytest.mark.slow
def test_a_resume_onto_other_data_is_refused_unless_allowed(tmp_path, tiny):
  data_dir, workdir = tmp_path / 'data', str(tmp_path / 'w')
  path, depth = _prepared(data_dir, tiny)
  trainer.train_and_evaluate(_config(data_dir, num_steps=2), workdir, log=lambda m: None)
  first = json.load(open(os.path.join(workdir, 'data.json')))
  assert first['file'] == path and first['identity']['sha256'] == identity.data_sha256(depth)
  arrays.save_array(path, depth * 1.01)  # replaced as prepare writes: same shape
  metrics = open(os.path.join(workdir, 'metrics.jsonl')).read()
  with pytest.raises(DataError, match=(
      rf'{re.escape(workdir)} was trained on other data than {re.escape(path)} holds now '
      r'\(same size, other contents, modified [^)]*\); restore that data to resume, or rerun '
      r'with --config\.data\.allow_changed=true')):
    trainer.train_and_evaluate(_config(data_dir, num_steps=4), workdir, log=lambda m: None)
  assert _saved(workdir) == [2]  # untouched
  assert open(os.path.join(workdir, 'metrics.jsonl')).read() == metrics
  logs, config = [], _config(data_dir, num_steps=4)
  config.data.allow_changed = True
  trainer.train_and_evaluate(config, workdir, log=logs.append)
  assert any(l.startswith('training on from step 2 on changed data (same size, other')
             for l in logs), logs
  records = [json.loads(l) for l in open(os.path.join(workdir, 'metrics.jsonl'))]
  assert [r['step'] for r in records if 'data_switched' in r] == [2]
  assert _saved(workdir) == [2, 4]
  record = json.load(open(os.path.join(workdir, 'data.json')))
  assert record['identity']['sha256'] == identity.data_sha256((depth * 1.01).astype(np.float32))
  assert [s['from']['sha256'] for s in record['switches']] == [first['identity']['sha256']]


def test_training_data_ignores_a_touch_and_a_copy_of_the_same_bytes(tmp_path, tiny):
  path, depth = _prepared(tmp_path, tiny)
  data = pipeline.TrainingData(str(tmp_path), tiny, memory_mb=1, log=lambda m: None)
  assert data.in_memory and data.changed() is None
  os.utime(path, ns=(time.time_ns(), time.time_ns() + 10**9))
  assert data.changed() is None
  arrays.save_array(path, depth)  # another file (inode), the same bytes
  assert data.changed() is None
  arrays.save_array(path, depth[::-1])
  assert data.changed().startswith('same size, other contents, modified ')
  os.remove(path)
  assert data.changed() == 'removed'
  with pytest.raises(DataError, match=r'changed during training \(removed\); stopped at step 7,'
                                      r' before saving; no checkpoint was saved yet'):
    data.check(7, None)


def test_a_split_other_than_meta_json_records_is_named_and_used(tmp_path, tiny):
  path, depth = _prepared(tmp_path, tiny)
  arrays.write_meta(str(tmp_path), {'identity': {'train': identity.of_file(path, whole=True)}})
  logs = []
  pipeline.TrainingData(str(tmp_path), tiny, memory_mb=1, log=logs.append)
  assert not [l for l in logs if 'meta.json' in l]
  np.save(path, depth[::-1])  # rewritten in place, not by prepare
  data = pipeline.TrainingData(str(tmp_path), tiny, memory_mb=1, log=logs.append)
  assert [l for l in logs if 'meta.json' in l] == [
      f'warning: {path} is not the file meta.json records (same size, other contents, '
      f'modified {identity.when(os.stat(path).st_mtime_ns)}); training on it as it is']
  np.testing.assert_array_equal(data.depth, depth[::-1])


@pytest.mark.slow
def test_a_split_read_from_its_file_cut_short_mid_run_is_one_line_not_a_bus_error(tmp_path):
  """The issue's bus error: the command line, reading the split from its file
  (data.memory_mb=0, as for a split too big for memory), its file truncated
  to half while it trains: exit 1 and one line naming the file and both
  sizes, no signal (in a subprocess, since a SIGBUS would end pytest)."""
  from dusty_jax.sensor import tiny_sensor
  path, _ = _prepared(tmp_path / 'data', tiny_sensor(16, 64), n=64)
  size = os.path.getsize(path)
  workdir = tmp_path / 'w'
  with _training(tmp_path, str(workdir), f'--config.data.dir={tmp_path / "data"}',
                 '--config.data.memory_mb=0') as proc:
    deadline = time.time() + 500
    while not (workdir / 'checkpoints' / '2').is_dir():
      assert proc.poll() is None, proc.communicate()[1][-3000:]
      assert time.time() < deadline, 'no checkpoint within the time allowed'
      time.sleep(0.2)
    with open(path, 'r+b') as f:
      f.truncate(size // 2)
    out, err = proc.communicate(timeout=300)
  assert proc.returncode == 1, err[-3000:]  # not -7 (SIGBUS) or 135
  lines = _messages(err)
  assert len(lines) == 1 and 'Traceback' not in err, err[-3000:]
  # Read by a batch first, or seen by the check at the log step: either names both.
  assert re.fullmatch(
      rf'error: {re.escape(path)}: cut short while training reads it: {size // 2:,} bytes '
      rf'where .* needs {size:,}; .*|error: {re.escape(path)} changed during training '
      rf'\(size {size:,} -> {size // 2:,} bytes.*', lines[0]), lines
  assert 'read from the file batch by batch (above data.memory_mb=0)' in out
