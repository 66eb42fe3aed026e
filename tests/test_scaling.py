"""benchmarks/scaling.py: a tiny run of the whole pipeline, its resumption, the
size rule; the scene kinds it splits the test scans by."""

import functools
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from dusty_jax import evaluation
from dusty_jax.data import scene, synthetic

BENCHMARKS = os.path.join(os.path.dirname(__file__), '..', 'benchmarks')
sys.path.insert(0, BENCHMARKS)  # the benchmarks import their siblings by bare name
import scaling  # noqa: E402

# A whole pipeline run in the module fixture (72 s on 2 cores): the slow set.
pytestmark = pytest.mark.slow

SIZES = ('c4-16_z16', 'c8-32_z32')
LENGTH_RUN = 'vlp16:64/c4-16_z16/0'


def _argv(workdir, out, cache):
  return ['--workdir', workdir, '--out', out, '--sensors', 'vlp16:64',
          '--sizes', ','.join(SIZES), '--seeds', '0', '--steps', '4', '--keep-every', '2',
          '--length-run', LENGTH_RUN, '--num-synthesis', '6', '--points', '32',
          '--synthesis-seeds', '1', '--num-restore', '4', '--invert-steps', '2',
          '--step-repeats', '2',
          '--set', 'data.num_synthetic=90', '--set', 'batch_size=8',
          '--set', 'checkpoint_every=2', '--set', 'log_every=2', '--set', 'image_every=100',
          '--set', f'data.cache={cache}']


def _finite(tree, path=''):
  """Every number in ``tree`` is finite (None allowed only where said)."""
  if isinstance(tree, dict):
    for k, v in tree.items():
      _finite(v, f'{path}.{k}')
  elif isinstance(tree, list):
    for i, v in enumerate(tree):
      _finite(v, f'{path}[{i}]')
  elif isinstance(tree, float):
    assert math.isfinite(tree), path


@pytest.fixture(scope='module')
def run(tmp_path_factory):
  root = tmp_path_factory.mktemp('scaling')
  argv = _argv(str(root / 'w'), str(root / 'out'), str(root / 'cache'))
  mp = pytest.MonkeyPatch()
  # Drop levels fitted to few iterations (the trainer and the length study call this).
  mp.setattr(evaluation, 'fit_levels',
             functools.partial(evaluation.fit_levels, num=16, num_steps=3))
  record = scaling.main(argv)
  yield root, argv, record
  mp.undo()


def test_record_has_every_figure_finite(run):
  root, _, record = run
  assert set(record['cells']) == {f'vlp16-64/{s}/seed0' for s in SIZES}
  on_disk = json.load(open(root / 'out' / 'scaling.json'))
  assert on_disk['cells'].keys() == record['cells'].keys() and 'machine' in on_disk
  assert os.path.getsize(root / 'out' / 'scaling.png') > 1000
  for key, cell in record['cells'].items():
    sp = cell['speed']
    assert sp['params_g'] > 0 and sp['params_d'] > 0 and sp['flops_per_step'] > 0
    assert sp['step_s'] > 0 and len(sp['step_times_s']) == 2
    assert sp['peak_rss_mib'] >= sp['peak_rss_train_mib'] > 0
    assert sp['machine']['cpus'] >= 1
    for b in ('1', '32'):
      assert sp['invert'][b]['seconds'] > 0 and sp['invert'][b]['iterations'] == 2
    for split in ('val', 'test'):
      ev = cell[split]
      assert set(ev['synthesis']['mean']) == {'jsd', 'cov', 'mmd', '1nna', 'swd'}
      assert set(ev['restoration']) >= set(scaling.CORRUPTIONS)
      assert 0 <= ev['inverted']['placement']['ece'] <= 1
      _finite(ev['synthesis'])
      _finite(ev['restoration'])
    kinds = cell['test']['kinds']
    assert set(kinds) <= set(scene.SCENE_KINDS)
    assert sum(k['scans'] for k in kinds.values()) == 9  # 90 // 10 test scans
    _finite(kinds)
  big, small = (record['cells'][f'vlp16-64/{s}/seed0']['speed'] for s in reversed(SIZES))
  assert big['params_g'] > small['params_g'] and big['flops_per_step'] > small['flops_per_step']
  # The length study: the length run at steps 2 and 4 (its end: the test figures).
  assert [p['step'] for p in record['length']] == [2, 4]
  run_ = record['cells']['vlp16-64/c4-16_z16/seed0']
  assert run_['length_0000004'] == run_['test']
  assert os.path.isfile(root / 'w' / 'vlp16-64' / 'c4-16_z16' / 'seed0' / 'length' /
                        'step0000002' / 'depth_levels.npz')
  assert record['chosen']['vlp16-64']['largest'] == 'c8-32_z32'
  assert record['chosen']['vlp16-64']['smallest'] in SIZES
  assert 'vlp16-64/c4-16_z16/seed0' in record['summary_md']


def test_rerun_skips_finished_work_and_resumes_a_killed_one(run, monkeypatch):
  root, argv, first = run
  def refuse(*args, **kwargs):
    raise AssertionError('finished work done again')
  for name in ('train', 'measure_in_subprocess', 'evaluate', 'with_fitted_levels'):
    monkeypatch.setattr(scaling, name, refuse)
  again = scaling.main(argv)
  assert again['cells'] == first['cells']
  # A call killed before its test section: only that section is done again.
  path = root / 'w' / 'vlp16-64' / 'c8-32_z32' / 'seed0' / scaling.EVAL_FILE
  data = json.load(open(path))
  del data['test']
  json.dump(data, open(path, 'w'))
  calls = []
  monkeypatch.setattr(scaling, 'evaluate',
                      lambda params, split, which, a, kinds=None: calls.append(which) or
                      {**first['cells']['vlp16-64/c8-32_z32/seed0']['test'], 'again': True})
  third = scaling.main(argv)
  assert calls == ['test']
  assert third['cells']['vlp16-64/c8-32_z32/seed0']['test']['again']
  # --speed-again: every trained cell's speed timed again, nothing else.
  timed = []
  monkeypatch.setattr(scaling, 'measure_in_subprocess',
                      lambda run, a: timed.append(os.path.basename(os.path.dirname(run))) or
                      {**first['cells']['vlp16-64/c4-16_z16/seed0']['speed'], 'again': True})
  fourth = scaling.main(argv + ['--speed-again'])
  assert sorted(timed) == sorted(SIZES) and calls == ['test']
  assert all(c['speed']['again'] for c in fourth['cells'].values())
  assert {k: {s: v for s, v in c.items() if s not in ('speed', 'seconds')}
          for k, c in fourth['cells'].items()} == {
      k: {s: v for s, v in c.items() if s not in ('speed', 'seconds')}
      for k, c in third['cells'].items()}
  # Without --seeds it times every seed trained, not the default seeds (0 here).
  other = root / 'w' / 'vlp16-64' / 'c4-16_z16' / 'seed3'
  other.mkdir()
  try:
    (other / scaling.EVAL_FILE).write_text(json.dumps({'train': {}}))
    timed.clear()
    i = argv.index('--seeds')
    seedless = argv[:i] + argv[i + 2:]
    scaling.main(seedless + ['--speed-again'])
    assert sorted(timed) == sorted(SIZES + ('c4-16_z16',))
  finally:
    for f in other.iterdir():
      f.unlink()
    other.rmdir()
  for untrained in (argv, seedless):
    with pytest.raises(SystemExit, match='no trained cell'):
      scaling.main(untrained + ['--speed-again', '--sizes', 'c2-4_z4'])


def test_smallest_within_spread_of_the_largest():
  sizes = {  # lower is better; 'L' has two seeds: thresholds 1.25 and 0.5
      'S': {'flops': 1, 'values': {'a': [1.0, 1.75], 'b': [0.25, 0.5]}},  # a's mean 1.375: out
      'M': {'flops': 2, 'values': {'a': [1.25], 'b': [0.5]}},  # at both thresholds: in
      'M2': {'flops': 3, 'values': {'a': [0.75], 'b': [0.25]}},  # in, but larger than M
      'L': {'flops': 4, 'values': {'a': [1.0, 1.25], 'b': [0.375, 0.5]}},
  }
  got = scaling.smallest_within_spread(sizes)
  assert got['largest'] == 'L' and got['thresholds'] == {'a': 1.25, 'b': 0.5}
  assert got['smallest'] == 'M'
  assert [s for s, v in got['verdicts'].items() if v['within']] == ['M', 'M2', 'L']
  sizes['S']['values']['a'] = [1.0, 1.5]  # mean 1.25: within now
  assert scaling.smallest_within_spread(sizes)['smallest'] == 'S'
  # One seed of the largest: no spread, its own values are the bar.
  one = {'S': {'flops': 1, 'values': {'a': [1.01]}}, 'L': {'flops': 2, 'values': {'a': [1.0]}}}
  assert scaling.smallest_within_spread(one)['smallest'] == 'L'


def test_peak_memory_is_the_subprocess_own_not_its_parents():
  # A parent holding 400 MiB runs a child: the child's ru_maxrss reports the
  # parent's peak (Linux carries it through fork and exec); peak_rss_mib must not.
  if not os.path.exists('/proc/self/status'):
    pytest.skip('no /proc here: peak_rss_mib falls back to ru_maxrss')
  child = ('import resource, sys; sys.path.insert(0, sys.argv[1]); import common; '
           'print(common.peak_rss_mib(), '
           'resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)')
  parent = ('import subprocess, sys; import numpy as np; held = np.ones(400 * 2**20 // 8); '
            f'print(subprocess.run([sys.executable, "-c", {child!r}, sys.argv[1]], '
            'capture_output=True, text=True, check=True).stdout)')
  out = subprocess.run([sys.executable, '-c', parent, BENCHMARKS], capture_output=True,
                       text=True, check=True).stdout
  own, maxrss = map(float, out.split())
  assert maxrss > 400  # the inherited figure: why ru_maxrss is not used
  assert own < 150  # an interpreter importing numpy: tens of MiB


def test_labels_of_close_points_keep_apart_and_inside():
  plt = scaling.common.pyplot()
  fig, ax = plt.subplots(figsize=(5, 4.2))  # a panel of the study's picture
  x = np.array([0.04, 0.1, 0.11, 0.12, 0.5])  # three in a clump mid-panel
  y = np.array([10.0, 8.0, 7.9, 8.05, 6.0])
  ax.plot(x, y, 'o-')
  ax.set_xscale('log')
  fig.tight_layout()
  names = ['c8-64_z64', 'c16-128_z64', 'c16-128_z128', 'c8-64_z128', 'c32-256_z128']
  scaling.label_points(ax, [(a, b, n, 'k') for a, b, n in zip(x, y, names)])
  renderer = fig.canvas.get_renderer()
  boxes = [t.get_window_extent(renderer) for t in ax.texts]
  assert [t.get_text() for t in ax.texts] == names  # one name per point, no leftovers
  assert not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:])
  assert all(ax.bbox.contains(b.x0, b.y0) and ax.bbox.contains(b.x1, b.y1) for b in boxes)
  plt.close(fig)


def test_scene_kind_from_the_seed_is_the_simulators():
  seeds = synthetic.scene_seeds(40, 2)
  kinds = [scene.kind_of(s) for s in seeds]
  assert kinds == [scene.build_scene(s)[2]['kind'] for s in seeds]
  assert set(kinds) == set(scene.SCENE_KINDS)


def test_scene_kinds_of_a_split_and_refusal(tmp_path):
  meta = {'dataset': 'synthetic', 'seed': 3, 'splits': {'train': 5, 'test': 4}}
  (tmp_path / 'meta.json').write_text(json.dumps(meta))
  got = synthetic.scene_kinds(str(tmp_path), 'test')
  want = [scene.build_scene((3 * 10 + synthetic.SPLIT_SEED_OFFSET['test']) * 1_000_003 + i)[2]
          ['kind'] for i in range(4)]
  assert list(got) == want
  with pytest.raises(ValueError, match='val'):
    synthetic.scene_kinds(str(tmp_path), 'val')
  (tmp_path / 'meta.json').write_text(json.dumps({'dataset': 'kitti', 'splits': {'test': 4}}))
  with pytest.raises(ValueError, match='simulated'):
    synthetic.scene_kinds(str(tmp_path), 'test')


def test_cells_and_configs():
  a = scaling.parse_args(['--sensors', 'kitti,vlp16:256', '--steps', '7'])
  got = scaling.cells(a)
  assert len(got) == 2 * (len(scaling.SIZES) + 2)
  assert ('kitti', scaling.SIZES[0], 1) in got and ('kitti', scaling.MAIN_SIZE, 1) not in got
  c = scaling.cell_config('vlp16:256', 'c32-256_z64', 1, a)
  main = scaling.experiment().get_config()
  assert (c.sensor.preset, c.sensor.width, c.ch_base, c.ch_max, c.latent_dim, c.seed) == (
      'vlp16', 256, 32, 256, 64, 1)
  assert c.num_steps == 7 and c.keep_every == scaling.KEEP_EVERY
  # The recipe is the main command's: everything but what the grid changes.
  changed = {'sensor', 'ch_base', 'ch_max', 'latent_dim', 'seed', 'num_steps', 'keep_every',
             'final_eval'}
  assert {k: v for k, v in c.to_dict().items() if k not in changed} == {
      k: v for k, v in main.to_dict().items() if k not in changed}
  with pytest.raises(ValueError, match='cBASE'):
    scaling.parse_size('16-128')


@pytest.mark.parametrize('name, sensor, size', [
    ('synthetic_vlp16.py', 'vlp16:256', 'c32-256_z128'),
    ('synthetic_c32.py', 'kitti', 'c32-256_z128'),
])
def test_the_experiment_is_the_cell_the_study_names(name, sensor, size):
  """Each size experiment trains what the study measured as its named size
  for that sensor (all but what only the study sets), and that size is the
  one the committed results name."""
  from dusty_jax import cli
  root = os.path.join(os.path.dirname(__file__), '..')
  with open(os.path.join(root, 'benchmarks', 'results', 'scaling.json')) as f:
    assert json.load(f)['chosen'][scaling.sensor_dir(sensor)]['smallest'] == size
  path = os.path.join(root, 'experiments', name)
  got = cli._load_config(path).to_dict()
  want = scaling.cell_config(sensor, size, 0, scaling.parse_args([])).to_dict()
  for c in (got, want):
    del c['keep_every'], c['final_eval']
  assert got == want
