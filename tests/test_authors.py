"""The authors' torch.save checkpoints load without torch (fixtures written by
real torch.save: tests/data/make_authors_fixture.py)."""

import json
import os
import pickle
import re
import shutil
import zipfile

import jax
import numpy as np
import pytest
import yaml

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


# Hand-written pickles of the kind torch.save writes, to forge what it never does.
def _str(s):
  return b'X' + len(s).to_bytes(4, 'little') + s.encode()


def _int(i):
  return pickle.BININT + i.to_bytes(4, 'little', signed=True)


def _tensor(size, stride, offset=0, storage_type='FloatStorage', key='0'):
  """Opcodes of _rebuild_tensor_v2(storage, offset, size, stride, False, OrderedDict())."""
  return (b'ctorch._utils\n_rebuild_tensor_v2\n' + pickle.MARK +
          pickle.MARK + _str('storage') + f'ctorch\n{storage_type}\n'.encode() + _str(key) +
          _str('cpu') + _int(4) + pickle.TUPLE + pickle.BINPERSID +
          _int(offset) + pickle.MARK + b''.join(map(_int, size)) + pickle.TUPLE +
          pickle.MARK + b''.join(map(_int, stride)) + pickle.TUPLE + pickle.NEWFALSE +
          b'ccollections\nOrderedDict\n' + pickle.EMPTY_TUPLE + pickle.REDUCE +
          pickle.TUPLE + pickle.REDUCE)


def _forge(path, body: bytes, storage: bytes, byteorder: str | None = None):
  with zipfile.ZipFile(path, 'w') as z:
    z.writestr('archive/data.pkl', pickle.PROTO + b'\x02' + body + pickle.STOP)
    z.writestr('archive/data/0', storage)
    if byteorder:
      z.writestr('archive/byteorder', byteorder)
  return str(path)


def test_forged_tensor_views_are_read_or_refused(tmp_path):
  """Offset, size and stride come from the file: a view reaching outside its
  storage would read the process's memory, so it is refused."""
  data = np.arange(4, dtype='<f4').tobytes()
  # A transposed view at offset 1: elements 1, 2 / 2, 3 -> [[1, 2], [2, 3]].
  got = authors.read_torch_checkpoint(_forge(tmp_path / 'v.pth', _tensor([2, 2], [1, 1], 1),
                                             data))
  np.testing.assert_array_equal(got, [[1, 2], [2, 3]])
  got = authors.read_torch_checkpoint(_forge(tmp_path / 't.pth', _tensor([2, 2], [1, 2]),
                                             data))
  np.testing.assert_array_equal(got, np.arange(4.0).reshape(2, 2).T)
  assert authors.read_torch_checkpoint(
      _forge(tmp_path / 'e.pth', _tensor([0, 3], [3, 1]), data)).shape == (0, 3)
  # Big-endian storages (a `byteorder` file, torch >= 2.1) are read as such.
  big = authors.read_torch_checkpoint(_forge(tmp_path / 'b.pth', _tensor([4], [1]),
                                             np.arange(4, dtype='>f4').tobytes(), 'big'))
  np.testing.assert_array_equal(big, np.arange(4.0))
  for i, (size, stride, offset, message) in enumerate([
      ([1000], [1], 0, 'reaches element 999 of a storage of 4'),
      ([2, 2], [2, 2], 0, 'reaches element 4 of a storage of 4'),
      ([4], [1], 1, 'reaches element 4'),
      ([2], [1], -2, 'offset -2 is not an index'),
      ([2], [-1], 3, 'stride -1 is not an index')]):
    path = _forge(tmp_path / f'bad{i}.pth', _tensor(size, stride, offset), data)
    with pytest.raises(pickle.UnpicklingError, match=re.escape(path) + '.*' + message):
      authors.read_torch_checkpoint(path)
  path = _forge(tmp_path / 'odd.pth', _tensor([1], [1]), data[:7])
  with pytest.raises(pickle.UnpicklingError, match='7 bytes, not a whole number'):
    authors.read_torch_checkpoint(path)
  path = _forge(tmp_path / 'bf16.pth', _tensor([1], [1], storage_type='BFloat16Storage'), data)
  with pytest.raises(pickle.UnpicklingError, match='torch.BFloat16Storage are not supported'):
    authors.read_torch_checkpoint(path)


def test_a_file_cannot_change_how_the_next_is_read(tmp_path):
  """BUILD on an allowed global (setting FloatStorage's dtype to another's,
  or a function's defaults) is refused; the next file reads as before."""
  attacks = [
      b'ctorch\nFloatStorage\n' + pickle.EMPTY_DICT + _str('dtype') +
      b'ctorch\nHalfStorage\n' + pickle.SETITEM + pickle.BUILD,
      b'ctorch\nFloatStorage\n' + pickle.NONE + pickle.EMPTY_DICT + _str('dtype') +
      _str('float16') + pickle.SETITEM + pickle.TUPLE2 + pickle.BUILD,
      b'ctorch._utils\n_rebuild_tensor_v2\n' + pickle.NONE + pickle.EMPTY_DICT +
      _str('__defaults__') + pickle.EMPTY_TUPLE + pickle.SETITEM + pickle.TUPLE2 +
      pickle.BUILD]
  for i, body in enumerate(attacks):
    with pytest.raises(pickle.UnpicklingError):
      authors.read_torch_checkpoint(_forge(tmp_path / f'a{i}.pth', body, b''))
  sd = authors.read_torch_checkpoint(os.path.join(DATA, 'authors_dusty1.pth'))
  assert sd['G_ema']['backbone.1.2.bias'].dtype == np.float32


def test_clear_errors(tmp_path):
  with pytest.raises(ValueError, match='not a torch.save checkpoint'):
    authors.read_torch_checkpoint(os.path.join(DATA, 'authors_dusty1_config.yaml'))
  # A file that is no checkpoint says so, before any config is looked for.
  with pytest.raises(ValueError, match="not a model file \\(an authors' .pth is a torch.save"):
    dusty_jax.load_checkpoint(os.path.join(DATA, 'authors_angles_resized.npy'))
  lone = tmp_path / 'lone.pth'
  shutil.copy(os.path.join(DATA, 'authors_dusty1.pth'), lone)
  with pytest.raises(FileNotFoundError, match='no config found'):
    dusty_jax.load_checkpoint(str(lone))
  # The dusty2 config asks for 2 confidence channels; the dusty1 file has 1.
  with pytest.raises(ValueError, match=r'confidence.*\(4, 1, 4, 4\) give head/kernel the shape \(4, 4, 4, 2\).*asks for \(4, 4, 4, 3\)'):
    dusty_jax.load_checkpoint(str(lone), config=os.path.join(DATA, 'authors_dusty2_config.yaml'))
  # The baseline's file lacks the 'backbone.' keys of DUSty, and the reverse.
  with pytest.raises(ValueError, match="holds a baseline generator .* names the dusty1"):
    dusty_jax.load_checkpoint(os.path.join(DATA, 'authors_baseline.pth'),
                              config=os.path.join(DATA, 'authors_dusty1_config.yaml'))
  with pytest.raises(ValueError, match="holds a DUSty generator .* names the baseline"):
    dusty_jax.load_checkpoint(str(lone),
                              config=os.path.join(DATA, 'authors_baseline_config.yaml'))
  sd = authors.read_torch_checkpoint(str(lone))['G_ema']
  del sd['backbone.2.2.bias']
  with pytest.raises(KeyError, match="missing key 'backbone.2.2.bias'"):
    authors._weights(sd, 'dusty1', 'lone')
  sd['backbone.2.2.bias'], sd['backbone.5.1.module.weight'] = np.zeros(8), np.zeros(1)
  with pytest.raises(ValueError, match=r"unexpected keys.*\['backbone.5.1.module.weight'\]"):
    authors._weights(sd, 'dusty1', 'lone')
  with pytest.raises(KeyError, match="no 'G_ema' in the checkpoint"):
    dusty_jax.load_checkpoint(os.path.join(DATA, 'authors_angles.pt'),
                              config=os.path.join(DATA, 'authors_dusty1_config.yaml'))
  with pytest.raises(ValueError, match='step= is for a run directory'):
    dusty_jax.load_checkpoint(os.path.join(DATA, 'authors_dusty1.pth'), step=3)


def _yaml(tmp_path, **changes):
  y = yaml.safe_load(open(os.path.join(DATA, 'authors_dusty1_config.yaml')))
  for dotted, value in changes.items():
    *parents, leaf = dotted.split('.')
    node = y
    for p in parents:
      node = node[p]
    node[leaf] = value
  path = tmp_path / 'changed.yaml'
  path.write_text(yaml.safe_dump(y))
  return str(path)


@pytest.mark.parametrize('changes, message', [
    ({'model.gen.arch': 'dusty3/dcgan_eqlr'}, r"unknown generator arch 'dusty3/dcgan_eqlr'"),
    ({'model.gen.arch': 'dusty1/dcgan'}, r"unknown generator arch 'dusty1/dcgan'"),
    ({'dataset.max_depth': 80.0}, r'depth range \(0.9, 80.0\)'),
    ({'model.gen.drop_const': 0}, r'drop_const=0.0'),
    ({'model.ring': False}, r'ring=false'),
])
def test_configs_dusty_jax_cannot_follow_are_refused(tmp_path, changes, message):
  with pytest.raises(ValueError, match=message):
    authors.config_from_yaml(_yaml(tmp_path, **changes))


def test_config_mapping():
  """Their sizes and sensors map onto ours: presets by shape, else a sensor
  of that shape."""
  c = authors.config_from_yaml(os.path.join(DATA, 'authors_dusty2_config.yaml'))
  assert (c.model, c.latent_dim, c.ch_base, c.ch_max, c.eqlr, c.tau) == (
      'dusty2', 8, 4, 8, 'authors', 1.0)
  assert (c.sensor.preset, c.sensor.height, c.sensor.width) == ('', 32, 64)


@pytest.mark.parametrize('shape, preset', [([64, 256], 'kitti'), ([32, 256], 'mpo')])
def test_config_presets(tmp_path, shape, preset):
  from dusty_jax import sensor as sensor_lib
  c = authors.config_from_yaml(_yaml(tmp_path, **{'dataset.shape': shape}))
  assert c.sensor.preset == preset
  assert sensor_lib.from_config(c.sensor).shape == tuple(shape)


def test_config_found_beside_the_checkpoint_or_in_its_hydra_run(tmp_path):
  released = tmp_path / 'dusty1_0025000000.pth'
  shutil.copy(os.path.join(DATA, 'authors_dusty1.pth'), released)
  shutil.copy(os.path.join(DATA, 'authors_dusty1_config.yaml'), tmp_path / 'dusty1_config.yaml')
  assert authors.find_config(str(released)) == str(tmp_path / 'dusty1_config.yaml')
  # Their training run: RUN/models/checkpoint_N.pth beside RUN/.hydra/config.yaml.
  (tmp_path / 'run' / 'models').mkdir(parents=True)
  (tmp_path / 'run' / '.hydra').mkdir()
  ckpt = tmp_path / 'run' / 'models' / 'checkpoint_0000001234.pth'
  shutil.copy(os.path.join(DATA, 'authors_dusty2.pth'), ckpt)
  shutil.copy(os.path.join(DATA, 'authors_dusty2_config.yaml'),
              tmp_path / 'run' / '.hydra' / 'config.yaml')
  params, config = dusty_jax.load_checkpoint(str(ckpt))
  assert config.model == 'dusty2' and params.variables['params']['head_bias'].shape == (3,)


def test_angles_from_their_dataset_file():
  """Their angles.pt, resized as their LiDAR class resizes it (PyTorch's
  output stored beside it), or a .npy table."""
  pth = os.path.join(DATA, 'authors_dusty1.pth')
  nominal, _ = dusty_jax.load_checkpoint(pth)
  params, _ = dusty_jax.load_checkpoint(pth, angles=os.path.join(DATA, 'authors_angles.pt'))
  want = np.load(os.path.join(DATA, 'authors_angles_resized.npy'))
  np.testing.assert_allclose(np.asarray(params.angles), want, atol=1e-6)
  assert np.abs(np.asarray(nominal.angles) - want).max() > 0.01
  npy, _ = dusty_jax.load_checkpoint(
      pth, angles=os.path.join(DATA, 'authors_angles_resized.npy'))
  np.testing.assert_array_equal(np.asarray(npy.angles), want)
  with pytest.raises(ValueError, match=r'angles of shape \(2, 32, 64\), expected'):
    authors.read_angles(os.path.join(DATA, 'authors_angles_resized.npy'),
                        params.sensor.with_width(32))


def test_bilinear_resize_by_hand():
  """Half-pixel centres: halving averages neighbour pairs, edges clamp."""
  a = np.arange(8.0).reshape(1, 1, 8)
  np.testing.assert_allclose(authors._resize_bilinear(a, (1, 4))[0, 0], [0.5, 2.5, 4.5, 6.5])
  np.testing.assert_allclose(authors._resize_bilinear(a[:, :, :2], (1, 4))[0, 0],
                             [0.0, 0.25, 0.75, 1.0])


def test_convert_makes_a_run_directory(tmp_path):
  from dusty_jax.tools import convert
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
  with pytest.raises(SystemExit, match="not a model file \\(an authors' .pth is a torch.save"):
    convert.main(['--pth', os.path.join(DATA, 'authors_angles_resized.npy'),
                  '--config', os.path.join(DATA, 'authors_dusty2_config.yaml'),
                  '--workdir', str(tmp_path / 'other')])
  with pytest.raises(SystemExit, match=r"data: a directory; give the authors' checkpoint file"):
    convert.main(['--pth', DATA, '--workdir', str(tmp_path / 'other')])


@pytest.mark.slow
def test_converted_run_with_a_dataset_serves_invert_and_evaluate(tmp_path):
  """--data_dir: the dataset's angle table, and the invert and evaluate
  command lines run on the converted run against that dataset."""
  from dusty_jax.tools import convert, evaluate, invert as invert_cli
  rng = np.random.default_rng(0)
  data = tmp_path / 'data'
  data.mkdir()
  angles = np.load(os.path.join(DATA, 'authors_angles_resized.npy'))
  np.save(data / 'angles.npy', angles)
  for split in ('train', 'test'):
    depth = rng.uniform(3, 60, (4, 32, 64)).astype(np.float32)
    depth[rng.uniform(size=depth.shape) < 0.2] = 0
    np.save(data / f'{split}.npy', depth)
  np.save(tmp_path / 'scan.npy', depth[0])
  work = str(tmp_path / 'run')
  convert.main(['--pth', os.path.join(DATA, 'authors_dusty1.pth'), '--workdir', work,
                '--data_dir', str(data)])
  params, config = dusty_jax.load_checkpoint(work)
  np.testing.assert_array_equal(np.asarray(params.angles), angles)
  assert config.data.dir == str(data)
  out = tmp_path / 'inverted'
  invert_cli.main(['--workdir', work, '--input', str(tmp_path / 'scan.npy'), '--steps', '3',
                   '--out', str(out)])
  m = np.load(out / 'scan_measurability.npy')
  assert m.shape == (32, 64) and ((m >= 0) & (m <= 1)).all()
  evaluate.main(['--workdir', work, '--num', '4', '--points', '32', '--seeds', '1'])
  ev = json.load(open(os.path.join(work, 'evaluation.json')))
  assert ev['num'] == 4 and set(ev['rows']) == {'dusty1', 'training set'}
  assert 0 <= ev['rows']['dusty1']['cov'][0] <= 1
