"""The evaluation protocol and its CLI on a tiny run."""

import json
import os
import subprocess
import sys
import tomllib

import jax
import numpy as np
import pytest

from dusty_jax import codec, metrics, writers
from dusty_jax.metrics import chamfer, point_sets, protocol, records
from conftest import FAST_COMPILE

HERE = os.path.dirname(__file__)


def _scans(sensor, n, seed=0, drop=0.0):
  rng = np.random.default_rng(seed)
  d = rng.uniform(3, 60, (n,) + sensor.shape).astype(np.float32)
  d[:, :2] = 0
  d[rng.uniform(size=d.shape) < drop] = 0
  return np.asarray(codec.encode(d, sensor)), d


def test_compare_identical_and_separated_sets(tiny):
  x, d = _scans(tiny, 6)
  angles = tiny.nominal_angles()
  cache = {}
  m = metrics.compare(x, x, angles, sensor=tiny, num_points=64, cache=cache)
  assert set(m) == {'jsd', 'cov', 'mmd', '1nna', 'swd'}
  assert m['cov'] == 1.0 and m['mmd'] < 1e-7 and abs(m['jsd']) < 1e-12
  assert cache['d_rr'].shape == (6, 6) and cache['real_clouds'].shape == (6, 64, 3)
  far = np.asarray(codec.encode(d * 0.3, tiny))
  m2 = metrics.compare(x, far, angles, sensor=tiny, num_points=64, cache=cache)
  assert m2['1nna'] == 1.0 and m2['jsd'] > 0.1 and m2['mmd'] > 0
  # The cache holds the real side only: reusing it changes nothing.
  assert m2 == metrics.compare(x, far, angles, sensor=tiny, num_points=64)
  with pytest.raises(ValueError, match='another real set'):
    metrics.compare(far, x, angles, sensor=tiny, num_points=64, cache=cache)
  with pytest.raises(ValueError, match='another real set'):
    metrics.compare(x, far, angles, sensor=tiny, num_points=64, cache=cache,
                    protocol='paper')
  with pytest.raises(ValueError, match='unknown protocol'):
    metrics.compare(x, far, angles, protocol='authors')
  table = records.format_table({'a': {k: [v, v] for k, v in m2.items()}})
  assert 'JSD x1e2' in table and '+-' in table
  legacy = {('nna' if k == '1nna' else k): [v] for k, v in m2.items()}
  assert records.format_table({'a': legacy}).splitlines()[-1] == \
      records.format_table({'a': {k: [v] for k, v in m2.items()}}).splitlines()[-1]


def test_compare_paper_protocol(tiny):
  """'paper' differs where the authors' code differs, and only there."""
  x, d = _scans(tiny, 8, seed=1, drop=0.2)
  y, _ = _scans(tiny, 8, seed=2, drop=0.2)
  angles = tiny.nominal_angles()
  ref = metrics.compare(x, y, angles, sensor=tiny, num_points=64)
  paper = metrics.compare(x, y, angles, sensor=tiny, num_points=64, protocol='paper')
  same = metrics.compare(x, x, angles, sensor=tiny, num_points=64, protocol='paper')
  assert 0.0015 < same['jsd'] < 0.003  # the eps bias: identical sets are not 0
  assert 5 < paper['swd'] / ref['swd'] < 15
  # COV, MMD and 1-NNA are the same functions of each protocol's clouds.
  clouds_r = protocol.prepare_set(x, angles, tiny, 64, protocol='paper')[0]
  clouds_f = protocol.prepare_set(y, angles, tiny, 64, protocol='paper')[0]
  np.testing.assert_array_equal(clouds_r[:, 0], 0.0)  # pixel 0 dropped: the origin
  d_rs = chamfer.pairwise(clouds_r, clouds_f, tile=16)
  mmd, cov = point_sets.mmd_cov(d_rs.T)
  assert paper['mmd'] == pytest.approx(mmd, rel=1e-6) and paper['cov'] == cov
  assert paper['jsd'] == pytest.approx(point_sets.jsd(clouds_r, clouds_f, protocol='paper'))
  # Without a sensor the shared 0.9-120 m range is used.
  assert metrics.compare(x, y, angles, num_points=64) == ref


def test_subset_rules():
  # The authors' [skip:limit:skip], written out as Python slicing of a list.
  for n, num in ((10, 5), (11, 5), (2000, 200), (7, 7), (9, 1)):
    skip = n // num
    want = list(range(n))[skip:skip * num + 1:skip]
    assert protocol.subset(n, num, 'paper').tolist() == want
  assert len(protocol.subset(10, 5, 'paper')) == 4  # num - 1 when num divides n
  assert protocol.subset(10, 5).tolist() == [0, 2, 4, 6, 9]
  assert protocol.subset(3, 5).tolist() == [0, 1, 2]
  with pytest.raises(ValueError, match='num <= 3'):
    protocol.subset(3, 5, 'paper')


def test_provenance_records_the_definition(tiny):
  rec = records.provenance('paper', 12, 64, [0, 1], protocol.SUBSET_RULES['paper'], tiny)
  assert rec['protocol'] == 'paper' and rec['num'] == 12 and rec['points'] == 64
  assert rec['seeds'] == [0, 1] and 'skip' in rec['subset']
  assert rec['sensor']['name'] == tiny.name and rec['sensor']['max_depth'] == 120.0
  assert len(rec['sensor']['elevation_deg']) == rec['sensor']['height'] == tiny.height
  with open(os.path.join(os.path.dirname(HERE), 'pyproject.toml'), 'rb') as f:
    assert rec['dusty_jax_version'] == tomllib.load(f)['project']['version']
  json.dumps(rec)


@pytest.mark.slow
def test_evaluate_cli(smoke_run, tmp_path):
  _, workdir, _ = smoke_run
  env = dict(os.environ)
  env['XLA_FLAGS'] = FAST_COMPILE  # one device
  r = subprocess.run([sys.executable, '-m', 'dusty_jax.tools.evaluate', '--workdir', workdir,
                      '--num', '4', '--points', '32', '--seeds', '2'], env=env,
                     capture_output=True, text=True, timeout=600)
  assert r.returncode == 0, r.stderr[-3000:]
  assert 'training set' in r.stdout and 'COV %' in r.stdout
  ev = json.load(open(os.path.join(workdir, 'evaluation.json')))
  row = ev['rows']['dusty1']
  assert len(row['jsd']) == 2 and all(0 <= c <= 1 for c in row['cov'])
  assert all(0 <= v <= 1 for v in row['1nna']) and all(v > 0 for v in row['mmd'])
  assert ev['protocol'] == 'reference' and ev['num'] == 4 and ev['points'] == 32
  assert ev['split'] == 'test'
  assert ev['seeds']['metric'] == [0, 1] and 'linspace' in ev['subset']
  assert ev['sensor']['height'] == 16 and ev['dusty_jax_version']
  # The paper's protocol, in process: its subset of 4 test scans has 3.
  from dusty_jax.tools import evaluate
  evaluate.main(['--workdir', workdir, '--num', '4', '--points', '32', '--seeds', '1',
                 '--protocol', 'paper', '--notrain_row'])
  ev = json.load(open(os.path.join(workdir, 'evaluation.json')))
  assert ev['protocol'] == 'paper' and ev['num'] == 3 and 'skip' in ev['subset']
  assert len(ev['rows']['dusty1']['jsd']) == 1
  # Against the validation split, written beside the test split's result.
  evaluate.main(['--workdir', workdir, '--num', '4', '--points', '32', '--seeds', '1',
                 '--protocol', 'paper', '--notrain_row', '--split', 'val'])
  val = json.load(open(os.path.join(workdir, 'evaluation_val.json')))
  assert val['split'] == 'val' and val['num'] == 3
  assert json.load(open(os.path.join(workdir, 'evaluation.json'))) == ev
  assert val['rows']['dusty1']['jsd'] != ev['rows']['dusty1']['jsd']  # other clouds


def test_tolerance_tuning_baseline(tiny, monkeypatch):
  """HyperOpt tunes beta for the baseline: it tries ``trials`` betas in the
  search range, and returns the one whose score was the lowest."""
  rng = np.random.default_rng(1)
  d = rng.uniform(3, 60, (16,) + tiny.shape).astype(np.float32)
  d[rng.uniform(size=d.shape) < 0.2] = 0
  val, gen = np.split(np.asarray(codec.encode(d, tiny)), 2)
  # A baseline's samples: no drops, but pixels near the drop value, which
  # betas in the search range drop or keep.
  near = rng.uniform(size=gen.shape) < 0.3
  gen = np.where(near, codec.ALPHA + rng.uniform(0, 0.2, gen.shape), np.maximum(gen, -0.5))
  tried = {}
  compare = protocol.compare

  def recorded(*args, tolerance, **kwargs):
    m = compare(*args, tolerance=tolerance, **kwargs)
    tried[tolerance] = protocol.tolerance_score(m)
    return m

  monkeypatch.setattr(protocol, 'compare', recorded)
  beta = protocol.tune_tolerance(val, gen, tiny.nominal_angles(), tiny, trials=6, points=32)
  assert len(tried) == 6 and all(1e-3 <= b <= 1e-1 for b in tried)
  assert len(set(tried.values())) > 1  # the betas tried score differently
  assert beta == pytest.approx(min(tried, key=tried.get), rel=1e-12)


def _cd_kdtree(a, b):
  from scipy.spatial import cKDTree
  return (np.mean(cKDTree(b).query(a)[0] ** 2) + np.mean(cKDTree(a).query(b)[0] ** 2))


def test_reconstruction_errors_both_protocols(tiny):
  """Table III per scan: the Chamfer distance over valid points (reference)
  or over every pixel with drops at the origin in both clouds (paper), each
  against a k-d tree; x_tilde = -1 is a 120 m range, not a drop."""
  from dusty_jax.metrics import reconstruction
  rng = np.random.default_rng(3)
  angles = tiny.nominal_angles()
  target = rng.uniform(2, 100, (2,) + tiny.shape).astype(np.float32)
  target[rng.uniform(size=target.shape) < 0.3] = 0
  target[:, 0, :4] = 119.0  # far returns, reconstructed as x_tilde = -1
  rec = target * rng.uniform(0.9, 1.1, target.shape).astype(np.float32)
  rec[rng.uniform(size=rec.shape) < 0.2] = 0
  x_tilde = np.array(codec.encode(np.where(rec > 0, rec, 50.0), tiny))
  x_tilde[:, 0, :4] = -1.0
  scan = np.asarray(codec.encode(rec, tiny))
  depth, valid = codec.decode(scan, tiny)
  result = {'inv_depth': x_tilde, 'valid': np.asarray(valid),
            'points': np.asarray(codec.to_points(depth, angles))}
  ref = reconstruction.errors(target, result, angles, tiny)
  paper = reconstruction.errors(target, result, angles, tiny, 'paper')
  pts_t = np.asarray(codec.to_points(target, angles)) / 120.0
  pts_r = result['points'] / 120.0
  vt = np.asarray(codec.valid_depth(target, tiny))
  for i in range(2):
    want_ref = _cd_kdtree(pts_t[i][vt[i]], pts_r[i][result['valid'][i]])
    full_t = np.where(vt[i][..., None], pts_t[i], 0).reshape(-1, 3)
    full_r = np.where(result['valid'][i][..., None], pts_r[i], 0).reshape(-1, 3)
    assert ref['cd'][i] == pytest.approx(want_ref, rel=1e-4)
    assert paper['cd'][i] == pytest.approx(_cd_kdtree(full_t, full_r), rel=1e-4)
    assert abs(paper['cd'][i] - ref['cd'][i]) > 0.05 * ref['cd'][i]
  # Depth errors are the same in both; -1 decodes to 120 m (AbsRel 1/119 there).
  for k in ('abs_rel', 'rmse', 'delta1'):
    np.testing.assert_array_equal(ref[k], paper[k])
  one = {'inv_depth': x_tilde[:1] * 0 - 1.0, 'valid': result['valid'][:1],
         'points': result['points'][:1]}
  only_far = np.zeros_like(target[:1])
  only_far[0, 0, :4] = 119.0
  errs = reconstruction.errors(only_far, one, angles, tiny)
  assert errs['abs_rel'][0] == pytest.approx(1 / 119, rel=1e-4)
  assert errs['delta1'][0] == 1.0


def test_invert_cli_records_protocol(smoke_run, tmp_path):
  from dusty_jax.tools import invert
  _, workdir, _ = smoke_run
  out = tmp_path / 'inv'
  invert.main(['--workdir', workdir, '--split', 'val', '--num', '2', '--steps', '2',
               '--protocol', 'paper', '--out', str(out)])
  m = json.load(open(out / 'metrics.json'))
  assert m['protocol'] == 'paper' and m['num'] == 2 and 'origin' in m['points']
  assert m['seeds']['seed'] == 0 and "split 'val'" in m['subset']
  assert m['sensor']['height'] == 16 and m['dusty_jax_version']
  assert len(m['per_scan']) == 2 and np.isfinite(m['mean']['cd'])


def test_synthesis_is_the_protocol_subset_over_seeds(tiny):
  """evaluation.synthesis (what the evaluate tool writes): the protocol's test
  subset, the samples of key(SAMPLE_SEED + s) against it per seed, and the
  training-set row on the same subset rule, each equal to protocol.compare
  called directly."""
  from dusty_jax import evaluation, sampling, trainer
  from train_helpers import tiny_config
  setup = trainer.make_setup(tiny_config(), tiny)
  state = trainer.init_state(setup, jax.random.key(0))
  params = trainer.generator_params(setup, state.g_params, tiny.nominal_angles())
  _, test = _scans(tiny, 8, seed=1, drop=0.1)
  _, train = _scans(tiny, 10, seed=2, drop=0.1)
  for name, n in (('reference', 4), ('paper', 3)):  # paper: skip 2, [2:9:2] of 8
    rec = evaluation.synthesis(params, test, train, num=4, points=16, seeds=2,
                               protocol_name=name)
    assert rec['num'] == n and rec['subset'] == protocol.SUBSET_RULES[name]
    assert rec['protocol'] == name and rec['seeds']['generator'] == [1000, 1001]
    row = rec['rows'][evaluation.row_label(params, params.tolerance)]
    ref = np.asarray(codec.encode(test[protocol.subset(8, 4, name)], tiny))
    assert len(ref) == n
    compare = lambda fake, seed: metrics.compare(ref, fake, params.angles, sensor=tiny,
                                                 protocol=name, num_points=16, seed=seed)
    for s in range(2):
      gen = sampling.sample_scans(params, jax.random.key(1000 + s), n)
      for k, v in compare(gen, s).items():
        assert row[k][s] == pytest.approx(v, rel=1e-6, abs=1e-9), (name, s, k)
    # The authors subsample train by the same rule and num; reference: n.
    tr = np.asarray(codec.encode(train[protocol.subset(10, 4 if name == 'paper' else n,
                                                       name)], tiny))[:n]
    for k, v in compare(tr, 0).items():
      assert rec['rows'][evaluation.TRAINING_ROW][k] == [pytest.approx(v, rel=1e-6)]
  label = evaluation.row_label(params, 0.0)
  assert label == 'dusty1' and set(rec['rows']) == {label, evaluation.TRAINING_ROW}
  assert list(evaluation.synthesis(params, test, None, num=4, points=16, seeds=1)
              ['rows']) == [label]
  json.dumps(rec)
  # One scan per set leaves 1-NNA nothing to compare with: said before sampling.
  for t, num in ((test, 1), (test[:1], 4)):
    with pytest.raises(ValueError, match=rf'at least 2 scans per set; num={num} of a test '
                                         rf'split of {len(t)} gives 1$'):
      evaluation.synthesis(params, t, None, num=num, points=16, seeds=1)


def test_after_training_reports_and_draws(smoke_run, tmp_path):
  """The short evaluation a training ends with: Table II on a few test scans,
  and drop placement of inverted test scans beside the per-ring table,
  equal to evaluation.restoration's on the same scans; a picture with a row
  per scan of titled panels (target, x_tilde, measurability, true return
  probability) and a colour bar in units under each column."""
  from PIL import Image
  from dusty_jax import evaluation, generator, sensor as sensor_lib
  from dusty_jax.data import arrays, pipeline
  config, workdir, _ = smoke_run
  params, _ = generator.load(workdir, log=lambda *_: None)
  data = pipeline.dataset_dir(config, sensor_lib.from_config(config.sensor), log=lambda m: None)
  rec = evaluation.after_training(params, data, str(tmp_path), num_synthesis=4, points=64,
                                  num_invert=3, invert_steps=3, picture_scans=2,
                                  progress=False)
  assert json.load(open(tmp_path / 'final_evaluation.json')) == json.loads(json.dumps(rec))
  assert rec['synthesis']['num'] == 4 and np.isfinite(rec['synthesis']['mmd'])
  test = arrays.load_split(data, 'test', params.sensor)
  direct = evaluation.restoration(params, test[:3], num_steps=3,
                                  truth=arrays.load_ground_truth(data, 'test', params.sensor, 3))
  assert rec['restoration']['abs_rel'] == pytest.approx(direct['mean']['abs_rel'])
  assert rec['ground_truth']['placement'] == pytest.approx(direct['ground_truth']['placement'],
                                                           nan_ok=True)
  within = rec['ground_truth']['ring_table']['auc_near_within_ring']
  assert within == 0.5 or np.isnan(within)  # a table knows nothing within a ring
  labels = writers.read_labels(str(tmp_path / 'final_evaluation.png'))
  assert labels['panels'] == [f'{t} (test scan {i})' for i in (1, 2) for t in (
      'target scan', 'reconstruction x_tilde', 'measurability', 'true return probability')]
  assert labels['colour bars'] == [writers.COLOUR_BAR[writers.DEPTH]] * 2 + [
      'probability of a return, as inverted', "probability of a return, the simulator's"]
  assert Image.open(tmp_path / 'final_evaluation.png').size[0] > 1000  # 4 panels wide
