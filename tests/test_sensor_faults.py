"""A folder of another sensor's sweeps, a spec that does not fit its data, a
malformed spec (issue 62): each refused or skipped in one line that says
what to fix, and nothing written that a rerun would trip over."""

import dataclasses
import json
import os
import re
import tracemalloc

import numpy as np
import pytest

from dusty_jax import configs, runs, sensor as sensor_lib, trainer
from dusty_jax.data import arrays, estimate, points, prepare, unfolding
from dusty_jax.errors import DataError
from dusty_jax.sensor import PRESETS
from dusty_jax.tools import prepare as prepare_tool
from test_sensors import _simulated_sweep
from train_helpers import tiny_config

# A 16-beam sensor as a user writes it (a VLP-16's beams, 256 of its 1800
# firings kept), and KITTI's HDL-64E seen at every firing.
MY16 = dataclasses.replace(PRESETS['vlp16'], name='my16', width=256)
HDL64 = dataclasses.replace(PRESETS['kitti'], width=2048, native_width=2048)


def _write_sweep(path, spec, seed, ring=False):
  """A simulated sweep of ``spec`` at every firing: (its points, its rows)."""
  _, xyz, rows = _simulated_sweep(dataclasses.replace(spec, width=spec.native_width), seed)
  fields = {'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2]}
  if ring:
    fields['ring'] = (spec.height - 1 - rows).astype(np.uint16)
  points.write_points(str(path), fields)
  return path


def _folder(root, sweeps):
  """``sweeps`` [(name, spec, seed)] written under root, all in the training
  split (train.txt)."""
  root.mkdir(parents=True, exist_ok=True)
  for name, spec, seed in sweeps:
    _write_sweep(root / name, spec, seed)
  (root / 'train.txt').write_text('\n'.join(name for name, _, _ in sweeps))
  return str(root)


MIXED = [(f'{i:03d}.bin', MY16, i) for i in range(4)] + [
    (f'kitti_{i:06d}.bin', HDL64, 100 + i) for i in range(2)]


def _refused(argv, out, match):
  """prepare's one error line for ``argv``, which must match; ``out`` not made."""
  with pytest.raises(SystemExit, match=match) as e:
    prepare_tool.main(argv)
  assert not os.path.exists(out), os.listdir(out)
  return str(e.value)


# --- Silently wrong before ---------------------------------------------------

def test_another_sensors_sweeps_in_the_folder_are_skipped_and_counted(tmp_path):
  root = _folder(tmp_path / 'raw', MIXED)
  out, logs = str(tmp_path / 'out'), []
  meta = prepare.prepare('files', root, out, MY16, log=logs.append)
  assert meta['splits'] == {'train': 4, 'val': 0, 'test': 0}
  foreign = {os.path.basename(s['path']): s['reason'] for s in meta['skipped']['train']}
  assert sorted(foreign) == ['kitti_000000.bin', 'kitti_000001.bin']
  for reason in foreign.values():
    assert re.search(r"not a sweep of sensor 'my16': [\d,]+ of its [\d,]+ returns on the beams "
                     r'and in range fill a pixel \([0-3]\.\d%\), where a sweep of the spec fills '
                     r'one per kept firing \(14\.2%: width 256 of native_width 1800\)', reason)
  assert "train: 4 scans written, 2 skipped (2 of another sensor than 'my16')" in logs
  # The array holds the four 16-beam sweeps, as each unfolds alone.
  want = [unfolding.unfold(points.read_points(os.path.join(root, n)), MY16).depth
          for n, _, _ in MIXED[:4]]
  np.testing.assert_array_equal(np.load(os.path.join(out, 'train.npy')), np.stack(want))


def _contents(folder):
  return {n: open(os.path.join(folder, n), 'rb').read() for n in sorted(os.listdir(folder))}


def test_a_rerun_on_only_another_sensors_sweeps_leaves_the_folder_as_it_was(tmp_path):
  out = str(tmp_path / 'out')
  prepare.prepare('files', _folder(tmp_path / 'mine', MIXED[:4]), out, MY16,
                  log=lambda m: None)
  before = _contents(out)
  foreign = _folder(tmp_path / 'kitti', MIXED[4:])
  with pytest.raises(DataError, match=(
      rf'^{re.escape(foreign)}: every scan file was skipped, nothing prepared; the first of '
      r"2: .*kitti_000000\.bin: not a sweep of sensor 'my16'")):
    prepare.prepare('files', foreign, out, MY16, log=lambda m: None)
  assert _contents(out) == before


def test_auto_on_sweeps_of_two_sensors_says_so_and_stops(tmp_path):
  root, out = _folder(tmp_path / 'raw', MIXED), str(tmp_path / 'out')
  line = _refused(['--dataset', 'files', '--root', root, '--out', out, '--sensor', 'auto'],
                  out, 'the sweeps to estimate from are of different sensors')
  assert re.search(r'kitti_00000\d\.bin shows 64 beams, .*/000\.bin 16 \(beam counts of all '
                   r'6: \[16, 16, 16, 16, 64, 64\]\); estimate from one sensor\'s sweeps', line)


def test_auto_on_beams_closer_than_the_data_tells_apart_stops(tmp_path):
  close = dataclasses.replace(MY16, elevation_deg=tuple(-5 - 0.001 * np.arange(16)))
  root = _folder(tmp_path / 'raw', [(f'{i}.bin', close, i) for i in range(3)])
  out = str(tmp_path / 'out')
  line = _refused(['--dataset', 'files', '--root', root, '--out', out, '--sensor', 'auto'],
                  out, 'found 1 beam in ')
  assert re.search(r'0\.bin and 2 more sweeps; the one at -5\.00\d degrees has [\d,]+ returns '
                   r'per sweep, 1[0-6]\.\d per firing of the 1800 measured: several beams '
                   r'merged; beams closer than 0\.01 degrees cannot be told apart', line)


def _prepared(directory, spec, n=8):
  """A prepared folder of ``spec``: random scans and its sensor.json."""
  os.makedirs(directory)
  rng = np.random.default_rng(0)
  depth = rng.uniform(2, 50, (n,) + spec.shape).astype(np.float32)
  np.save(arrays.split_path(str(directory), 'train'), depth)
  sensor_lib.save(spec, os.path.join(directory, arrays.SENSOR))
  return str(directory)


def _train_config(data_dir, sensor_file=''):
  c = tiny_config(num_steps=2, checkpoint_every=2, log_every=1, image_every=1000)
  c.data.dir = data_dir
  c.sensor.file = sensor_file
  return c


def test_training_with_a_spec_other_than_the_datas_is_refused(tmp_path):
  config = tiny_config()
  data_spec = dataclasses.replace(sensor_lib.from_config(config.sensor), name='a',
                                  max_depth=80.0)
  data = _prepared(tmp_path / 'data', data_spec)
  other = str(tmp_path / 'b.json')
  sensor_lib.save(dataclasses.replace(data_spec, name='b', max_depth=120.0), other)
  workdir = tmp_path / 'run'
  mine = re.escape(os.path.join(data, 'sensor.json'))
  for given, named in ((other, re.escape(f'sensor.file={other}')),
                       ('', r'a tiny sensor of 16x64')):  # (no spec: the config's own)
    with pytest.raises(DataError, match=(
        rf'^{mine}, the spec the data was prepared with, is not the config\'s \({named}\): '
        rf'max_depth: data 80\.0, config 120\.0; train with --config\.sensor\.file={mine}$')):
      trainer.train_and_evaluate(_train_config(data, given), str(workdir), log=lambda m: None)
    assert not workdir.exists()
  # Its own spec at other columns (--config.sensor.width): both flags named.
  with pytest.raises(DataError, match=(
      rf'\(x\): width: data 64, config 32; train with --config\.sensor\.file={mine} '
      r'--config\.sensor\.width=64$')):
    arrays.check_sensor(data, sensor_lib.with_columns(data_spec, 32), 'x')
  # The data's own spec, under any name, passes.
  renamed = str(tmp_path / 'renamed.json')
  sensor_lib.save(dataclasses.replace(data_spec, name='renamed'), renamed)
  arrays.check_sensor(data, sensor_lib.load(renamed), 'x')


# --- One line that says what to fix -------------------------------------------

def test_a_spec_of_far_more_beams_than_the_sweeps_rings(tmp_path):
  sweeps = dataclasses.replace(MY16, width=64, native_width=512)
  root = tmp_path / 'raw'
  for i in range(2):
    _write_sweep(root / f'{i}.pcd.bin', sweeps, i, ring=True)
  spec = str(tmp_path / 'big.json')
  sensor_lib.save(dataclasses.replace(sweeps, name='big',
                                      elevation_deg=tuple(np.linspace(15, -15, 10000))), spec)
  out = str(tmp_path / 'out')
  line = _refused(['--dataset', 'files', '--root', str(root), '--out', out, '--sensor', spec],
                  out, 'every scan file was skipped, nothing prepared; the first of 2: ')
  assert re.search(r"\.pcd\.bin: returns on only 16 of the 10000 rows of sensor 'big', those "
                   r"\d+% full: a sweep of 16 beams, not of the spec's 10000; is the spec the "
                   "data's sensor\\?$", line)


@pytest.mark.parametrize('field, value, says', [
    ('elevation_deg', '[15, 13, 11]', 'elevation_deg must be a list of numbers, one per beam, '
     'top beam first, got "[15, 13, 11]"'),
    ('elevation_deg', '9753', 'elevation_deg must be a list of numbers, one per beam, top beam '
     'first, got "9753"'),
    ('elevation_deg', list(np.linspace(80, -80, 2 ** 16 + 1)), 'elevation_deg lists 65,537 '
     "beams; a spec holds at most 65,536 (a ring id is 16 bits in the drivers' formats)"),
    ('width', True, 'width must be an integer, got true'),
])
def test_a_spec_field_of_the_wrong_type_is_named(tmp_path, field, value, says):
  root = tmp_path / 'raw'
  _write_sweep(root / '0.bin', MY16, 0)
  spec = tmp_path / 'bad.json'
  spec.write_text(json.dumps(dict(MY16.to_dict(), **{field: value})))
  out = str(tmp_path / 'out')
  line = _refused(['--dataset', 'files', '--root', str(root), '--out', out, '--sensor',
                   str(spec)], out, re.escape(says))
  assert line == f'error: {spec}: {says}'
  c = configs.default()  # and where training reads it
  c.sensor.file = str(spec)
  with pytest.raises(configs.ConfigError, match=re.escape(f'{spec}: {says}')):
    configs.validate(c)


def test_a_split_writer_that_cannot_map_its_file_leaves_none(tmp_path, monkeypatch):
  def no_memory(*args, **kwargs):
    open(args[0], 'wb').close()  # as open_memmap leaves it when mmap fails
    raise OSError(12, 'Cannot allocate memory')
  monkeypatch.setattr(np.lib.format, 'open_memmap', no_memory)
  with pytest.raises(OSError, match='Cannot allocate memory'):
    arrays.SplitWriter(str(tmp_path / 'train.npy'), 10 ** 6, (16, 256))
  assert os.listdir(tmp_path) == []


def test_a_pickled_angle_table_is_named_before_the_run_folder_is_made(tmp_path):
  data = _prepared(tmp_path / 'data', sensor_lib.from_config(tiny_config().sensor))
  os.remove(os.path.join(data, arrays.SENSOR))
  angles = os.path.join(data, arrays.ANGLES)
  np.save(angles, np.array([{'run': 'code'}], dtype=object), allow_pickle=True)
  workdir = tmp_path / 'run'
  with pytest.raises(DataError, match=rf'^{re.escape(angles)}: holds Python objects \(object\), '
                     'not numbers$'):
    trainer.train_and_evaluate(_train_config(data), str(workdir), log=lambda m: None)
  assert not workdir.exists()


def test_a_pattern_that_matches_nothing_says_what_is_there(tmp_path):
  root = tmp_path / 'raw'
  for i in range(3):
    _write_sweep(root / f'{i}.bin', MY16, i)
  (root / 'notes.md').write_text('x')
  out = str(tmp_path / 'out')
  line = _refused(['--dataset', 'files', '--root', str(root), '--out', out, '--sensor',
                   'vlp16', '--pattern', '*.pcd'], out, 'no files under it')
  assert line == (f"error: {root}: no files under it match --pattern '*.pcd' (it holds 3 .bin, "
                  '1 .md; point files end in .bin, .npy, .pcap, .pcd, .pcd.bin, .ply, '
                  'recordings in .bag, .db3, .mcap)')


def test_auto_on_a_sweep_of_noise_finds_no_beams_in_little_memory(tmp_path):
  root = tmp_path / 'raw'
  rng = np.random.default_rng(0)
  noise = rng.uniform(-50, 50, (120_000, 3))
  points.write_points(str(root / 'noise.bin'), dict(zip('xyz', noise.T)))
  out = str(tmp_path / 'out')
  line = _refused(['--dataset', 'files', '--root', str(root), '--out', out, '--sensor', 'auto'],
                  out, 'no beam structure found')
  assert re.search(r'noise\.bin: no beam structure found: the elevations of its returns '
                   r'\(-7\d\.\d to 7\d\.\d degrees, 1st-99th percentile\) fall into [\d,]+ '
                   r'clusters, more than the 1024 beams', line)
  tracemalloc.start()  # numpy's arrays count (it reports them to tracemalloc)
  with pytest.raises(DataError, match='no beam structure'):
    estimate.estimate([noise])
  peak = tracemalloc.get_traced_memory()[1]
  tracemalloc.stop()
  assert peak < 200 * 2 ** 20, peak  # an (N, clusters) matrix took 1.7 GB


def test_auto_skips_an_empty_file_in_one_line(tmp_path):
  root = tmp_path / 'raw'
  for i in range(4):
    _write_sweep(root / f'{i}.bin', MY16, i)
  (root / '0.bin').write_bytes(b'')
  (root / 'train.txt').write_text('\n'.join(f'{i}.bin' for i in range(4)))
  out, logs = str(tmp_path / 'out'), []
  meta = prepare.prepare('files', str(root), out, auto_sensor=True, log=logs.append)
  empty = f'skipped: {root / "0.bin"}: empty file'
  assert logs[0] == empty and logs.count(empty) == 2  # the estimate, then the conversion
  assert meta['splits']['train'] == 3
  assert len(np.load(os.path.join(out, 'train.npy'))) == 3


def _run_of(workdir, spec_file):
  """A run directory as training leaves it, trained with ``spec_file``."""
  c = tiny_config()
  c.sensor.file = spec_file
  spec = configs.validate(c)
  runs.record(workdir, c, spec, configs.model_settings(c), spec.nominal_angles())
  open(os.path.join(workdir, 'train.lock'), 'w').close()  # (each run keeps its lock)
  return _files(workdir)


def _files(workdir):
  """{name: contents} of a run directory, but its lock's holder."""
  return {n: b'' if n == 'train.lock' else open(os.path.join(workdir, n), 'rb').read()
          for n in os.listdir(workdir)}


def test_a_resume_without_the_runs_spec_file_names_the_first_difference(tmp_path):
  spec = str(tmp_path / 'my.json')
  sensor_lib.save(dataclasses.replace(MY16, width=64, native_width=512), spec)
  workdir = str(tmp_path / 'run')
  before = _run_of(workdir, spec)
  with pytest.raises(configs.ConfigError) as e:
    trainer.train_and_evaluate(tiny_config(), workdir, log=lambda m: None)
  assert str(e.value) == (
      f'{workdir} holds a run of another architecture (sensor.elevation_deg[0]: run 15.0, '
      f'config 2.0 (the run trained with sensor.file={spec}; the config gives a tiny sensor '
      "of 16x64)); its checkpoints cannot be resumed with this config. Use another "
      "--workdir, or the run's own values.")
  assert _files(workdir) == before


def test_a_resume_after_editing_the_spec_names_the_field(tmp_path):
  spec = str(tmp_path / 'my.json')
  mine = dataclasses.replace(MY16, width=64, native_width=512)
  sensor_lib.save(mine, spec)
  workdir = str(tmp_path / 'run')
  before = _run_of(workdir, spec)
  sensor_lib.save(dataclasses.replace(mine, max_depth=80.0), spec)
  config = tiny_config()
  config.sensor.file = spec
  with pytest.raises(configs.ConfigError, match=re.escape(
      f'(sensor.max_depth: run 100.0, config 80.0 (the run trained with sensor.file={spec}; '
      f'the config gives sensor.file={spec}))')):
    trainer.train_and_evaluate(config, workdir, log=lambda m: None)
  assert _files(workdir) == before
