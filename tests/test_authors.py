"""The authors' torch.save checkpoints load without torch (fixtures written by
real torch.save: tests/data/make_authors_fixture.py)."""

import io
import os
import pickle
import shutil
import zipfile

import jax
import numpy as np
import pytest

import dusty_jax
from dusty_jax import authors

DATA = os.path.join(os.path.dirname(__file__), 'data')


@pytest.mark.parametrize('model', ['baseline', 'dusty1', 'dusty2'])
def test_outputs_equal_the_authors_pytorch_outputs(model):
  params, config = dusty_jax.load_checkpoint(os.path.join(DATA, f'authors_{model}.pth'))
  assert (config.model, params.sensor.shape, params.latent_dim, config.source_step) == (
      model, (32, 64), 8, 1234)
  ref = np.load(os.path.join(DATA, f'authors_{model}_outputs.npz'))
  out = dusty_jax.generate(params, ref['z'], jax.random.key(0))
  np.testing.assert_allclose(np.asarray(out['inv_depth']), ref['depth_orig'], atol=2e-5)
  if model == 'dusty1':
    want = 1 / (1 + np.exp(-ref['confidence'][..., 0]))
  elif model == 'dusty2':
    c = ref['confidence']
    want = 1 / (1 + np.exp(-c[..., 0])) * (c[..., 1] > 0)
  else:
    want = np.ones_like(ref['depth_orig'])
  np.testing.assert_allclose(np.asarray(out['measurability']), want, atol=2e-5)


def test_g_ema_is_the_default_and_g_differs():
  path = os.path.join(DATA, 'authors_dusty1.pth')
  ema, _ = dusty_jax.load_checkpoint(path)
  raw, _ = dusty_jax.load_checkpoint(path, ema=False)
  sd = authors.read_torch_checkpoint(path)
  w = np.asarray(sd['G_ema']['backbone.1.2.bias'])
  np.testing.assert_array_equal(np.asarray(ema.variables['params']['up1_bias']), w)
  assert not np.allclose(np.asarray(raw.variables['params']['up1_bias']), w)


def test_reader_builds_arrays_with_offsets_and_strides():
  """The optimiser states and every tensor come back as plain numpy."""
  sd = authors.read_torch_checkpoint(os.path.join(DATA, 'authors_dusty2.pth'))
  assert sd['step'] == 1234 and set(sd) >= {'G', 'D', 'G_ema', 'optim_G', 'optim_D'}
  w = sd['G']['backbone.0.0.module.weight']
  assert isinstance(w, np.ndarray) and w.dtype == np.float32 and w.shape == (8, 8, 2, 4)
  st = sd['optim_G']['state'][0]
  assert st['exp_avg'].shape == sd['G']['backbone.0.0.module.weight'].shape


def _with_pickle(src, dst, payload: bytes):
  with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, 'w') as zout:
    for item in zin.infolist():
      data = zin.read(item.filename)
      zout.writestr(item, payload if item.filename.endswith('/data.pkl') else data)


class _Evil:
  def __reduce__(self):
    return (os.system, ('echo pwned > ' + _Evil.marker,))


def test_a_pickle_that_would_run_code_is_refused(tmp_path):
  _Evil.marker = str(tmp_path / 'pwned')
  bad = tmp_path / 'evil.pth'
  _with_pickle(os.path.join(DATA, 'authors_dusty1.pth'), bad,
               pickle.dumps({'G_ema': _Evil()}, protocol=2))
  shutil.copy(os.path.join(DATA, 'authors_dusty1_config.yaml'), tmp_path / 'evil_config.yaml')
  with pytest.raises(pickle.UnpicklingError, match=r'refusing the global (posix|os)\.system'):
    dusty_jax.load_checkpoint(str(bad))
  assert not (tmp_path / 'pwned').exists()


def test_clear_errors(tmp_path):
  with pytest.raises(ValueError, match='not a torch.save checkpoint'):
    authors.read_torch_checkpoint(os.path.join(DATA, 'authors_dusty1_config.yaml'))
  lone = tmp_path / 'lone.pth'
  shutil.copy(os.path.join(DATA, 'authors_dusty1.pth'), lone)
  with pytest.raises(FileNotFoundError, match='no config beside it'):
    dusty_jax.load_checkpoint(str(lone))
  # The dusty2 config asks for 2 confidence channels; the dusty1 file has 1.
  with pytest.raises(ValueError, match=r'head/kernel has shape \(4, 4, 4, 2\).*\(4, 4, 4, 3\)'):
    dusty_jax.load_checkpoint(str(lone), config=os.path.join(DATA, 'authors_dusty2_config.yaml'))
  # The baseline's file lacks the 'backbone.' keys DUSty expects.
  with pytest.raises(KeyError, match="missing key 'backbone.0.0.module.weight'"):
    dusty_jax.load_checkpoint(os.path.join(DATA, 'authors_baseline.pth'),
                              config=os.path.join(DATA, 'authors_dusty1_config.yaml'))


def test_convert_makes_a_run_directory(tmp_path):
  from dusty_jax import convert
  pth = os.path.join(DATA, 'authors_dusty2.pth')
  work = str(tmp_path / 'run')
  convert.main(['--pth', pth, '--workdir', work])
  direct, _ = dusty_jax.load_checkpoint(pth)
  run, config = dusty_jax.load_checkpoint(work)
  assert config.model == 'dusty2' and config.eqlr == 'authors'
  for a, b in zip(jax.tree.leaves(direct.variables), jax.tree.leaves(run.variables)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  np.testing.assert_array_equal(np.asarray(run.angles), np.asarray(direct.angles))
  with pytest.raises(SystemExit, match='already holds a run'):
    convert.main(['--pth', pth, '--workdir', work])
