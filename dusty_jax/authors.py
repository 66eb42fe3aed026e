"""The authors' released PyTorch checkpoints (kazuto1011/dusty-gan), without torch.

    params, config = dusty_jax.load_checkpoint('dusty1_0025000000.pth')   # yaml beside it
    params, config = dusty_jax.load_checkpoint('x.pth', config='config.yaml')

A ``torch.save`` file is a zip holding ``*/data.pkl`` (a pickle of the
structure) and ``*/data/N`` (the raw bytes of each tensor storage). It is
read here with a restricted unpickler: only the few globals a state dict
needs (OrderedDict, torch's tensor rebuild functions and storage types) are
known, each mapped to a numpy stand-in; any other global is refused before
anything runs, so a checkpoint from the internet cannot execute code.

The generator's weights (``G_ema`` by default, as the authors' own loader;
``ema=False`` for ``G``) are mapped onto dusty_jax's parameters, whose eq-lr
constants are the authors' (``eqlr='authors'``), so the function is theirs.
The angle table is not in their checkpoint: the sensor's nominal angles are
used unless ``angles`` names a (2, H, W) ``.npy``.
"""

from __future__ import annotations

import collections
import os
import pickle
import zipfile

import numpy as np

_DTYPES = {'FloatStorage': np.float32, 'DoubleStorage': np.float64,
           'HalfStorage': np.float16, 'LongStorage': np.int64,
           'IntStorage': np.int32, 'ShortStorage': np.int16,
           'CharStorage': np.int8, 'ByteStorage': np.uint8,
           'BoolStorage': np.bool_}


class _StorageType:
  def __init__(self, name):
    self.dtype = np.dtype(_DTYPES[name])


def _rebuild_tensor(storage, offset, size, stride, *unused):
  itemsize = storage.dtype.itemsize
  if not size:
    return storage[offset].copy()
  view = np.lib.stride_tricks.as_strided(
      storage[offset:], shape=tuple(size), strides=tuple(s * itemsize for s in stride))
  return np.array(view)


def _rebuild_parameter(data, *unused):
  return data


_ALLOWED = {
    ('collections', 'OrderedDict'): collections.OrderedDict,
    ('torch._utils', '_rebuild_tensor_v2'): _rebuild_tensor,
    ('torch._utils', '_rebuild_parameter'): _rebuild_parameter,
}
_ALLOWED.update({('torch', name): _StorageType(name) for name in _DTYPES})


class _Unpickler(pickle.Unpickler):
  def __init__(self, file, zf: zipfile.ZipFile, prefix: str, source: str):
    super().__init__(file)
    self.zf, self.prefix, self.source = zf, prefix, source

  def find_class(self, module, name):
    try:
      return _ALLOWED[(module, name)]
    except KeyError:
      raise pickle.UnpicklingError(
          f'{self.source}: refusing the global {module}.{name}: a checkpoint holds '
          'tensors and dicts only, so this file is not one (or it tries to run code)'
          ) from None

  def persistent_load(self, pid):
    if not (isinstance(pid, tuple) and pid and pid[0] == 'storage'):
      raise pickle.UnpicklingError(f'{self.source}: unknown persistent id {pid!r}')
    storage_type, key = pid[1], pid[2]
    if not isinstance(storage_type, _StorageType):
      raise pickle.UnpicklingError(f'{self.source}: unknown storage type {storage_type!r}')
    raw = self.zf.read(f'{self.prefix}/data/{key}')
    return np.frombuffer(raw, dtype=storage_type.dtype.newbyteorder('<'))


def read_torch_checkpoint(path: str):
  """The object a ``torch.save`` zip file holds, tensors as numpy arrays."""
  if not zipfile.is_zipfile(path):
    raise ValueError(f'{path}: not a torch.save checkpoint (not a zip file; the '
                     'legacy non-zip torch format is not supported)')
  with zipfile.ZipFile(path) as zf:
    pkl = [n for n in zf.namelist() if n.endswith('/data.pkl')]
    if len(pkl) != 1:
      raise ValueError(f'{path}: not a torch.save checkpoint (no single data.pkl)')
    prefix = pkl[0][:-len('/data.pkl')]
    with zf.open(pkl[0]) as f:
      return _Unpickler(f, zf, prefix, path).load()


# ----------------------------------------------------------------------------
# Their config and key layout -> ours.
# ----------------------------------------------------------------------------

_ARCH = {'none': 'baseline', 'dusty1': 'dusty1', 'dusty2': 'dusty2'}


def find_config(path: str) -> str:
  """The yaml beside a .pth: STEM_config.yaml, PREFIX_config.yaml, config.yaml."""
  d, stem = os.path.dirname(path), os.path.splitext(os.path.basename(path))[0]
  names = [f'{stem}_config.yaml', f'{stem.split("_")[0]}_config.yaml', 'config.yaml',
           os.path.join('.hydra', 'config.yaml')]
  for n in names:
    if os.path.isfile(os.path.join(d, n)):
      return os.path.join(d, n)
  raise FileNotFoundError(f'{path}: no config beside it (looked for {names}); pass '
                          "config='...yaml', the authors' config of that run")


def config_from_yaml(path: str):
  """Our ConfigDict from the authors' hydra config of a run."""
  import yaml
  from dusty_jax import configs
  with open(path) as f:
    y = yaml.safe_load(f)
  try:
    gen, shape = y['model']['gen'], list(y['dataset']['shape'])
    masker = gen['arch'].split('/')[0]
  except (KeyError, TypeError, AttributeError) as e:
    raise ValueError(f'{path}: not a dusty-gan run config (missing {e})') from None
  if masker not in _ARCH or not gen['arch'].endswith('dcgan_eqlr'):
    raise ValueError(f'{path}: unknown generator arch {gen["arch"]!r}')
  if not y['model'].get('ring', True):
    raise ValueError(f'{path}: ring=false (reflect padding) is not supported')
  c = configs.default()
  c.model = _ARCH[masker]
  c.latent_dim, c.ch_base, c.ch_max = int(gen['in_ch']), int(gen['ch_base']), int(gen['ch_max'])
  c.tau = float(gen.get('tau', 1.0))
  c.eqlr = 'authors'
  depths = (float(y['dataset'].get('min_depth', 0.9)), float(y['dataset'].get('max_depth', 120.0)))
  preset = {(64, 256): 'kitti', (32, 256): 'mpo'}.get(tuple(shape), '')
  if preset and depths == (0.9, 120.0):
    c.sensor.preset = preset
  else:
    c.sensor.preset, c.sensor.height, c.sensor.width = '', shape[0], shape[1]
  c.data.name = str(y['dataset'].get('name', ''))
  return c


def _weights(sd: dict, model: str, source: str) -> dict:
  """Their generator state dict -> our Flax ``params`` (numpy)."""
  pre = '' if model == 'baseline' else 'backbone.'

  def get(k):
    if pre + k not in sd:
      raise KeyError(f'{source}: missing key {pre + k!r} in the generator state dict')
    return np.asarray(sd[pre + k], np.float32)

  w = get('0.0.module.weight')  # (latent, C, h0, w0)
  p = {'proj': w.transpose(0, 2, 3, 1).reshape(w.shape[0], -1),
       'proj_bias': get('0.1.bias')}
  for i in (1, 2, 3):
    p[f'up{i}'] = {'kernel': get(f'{i}.1.module.weight').transpose(2, 3, 0, 1)}
    p[f'up{i}_bias'] = get(f'{i}.2.bias')
  heads = ['depth'] + ([] if model == 'baseline' else ['confidence'])
  kern = np.concatenate([get(f'4.heads.{h}.1.module.weight') for h in heads], axis=1)
  p['head'] = {'kernel': kern.transpose(2, 3, 0, 1)}
  p['head_bias'] = np.concatenate([get(f'4.heads.{h}.1.module.bias') for h in heads])
  return p


def load(path: str, config: str | None = None, ema: bool = True,
         angles: str | None = None):
  """(GeneratorParams, config) of an authors' ``.pth`` checkpoint."""
  import jax
  import jax.numpy as jnp
  from dusty_jax import models, sensor as sensor_lib
  cfg = config_from_yaml(config or find_config(path))
  ckpt = read_torch_checkpoint(path)
  key = 'G_ema' if ema else 'G'
  if not isinstance(ckpt, dict) or key not in ckpt:
    raise KeyError(f'{path}: no {key!r} in the checkpoint (keys: '
                   f'{sorted(ckpt) if isinstance(ckpt, dict) else type(ckpt).__name__})')
  sensor = sensor_lib.from_config(cfg.sensor)
  module = models.build_generator(cfg.model, sensor, cfg.latent_dim, cfg.ch_base,
                                  cfg.ch_max, eqlr='authors')
  want = jax.eval_shape(module.init, jax.random.key(0), jnp.zeros((1, cfg.latent_dim)))
  got = {'params': _weights(ckpt[key], cfg.model, path)}
  flat_want = {'/'.join(str(k.key) for k in p): v.shape
               for p, v in jax.tree_util.tree_leaves_with_path(want)}
  flat_got = {'/'.join(str(k.key) for k in p): v.shape
              for p, v in jax.tree_util.tree_leaves_with_path(got)}
  for k, shape in flat_want.items():
    if flat_got.get(k) != shape:
      raise ValueError(f'{path}: {key} weight for {k} has shape {flat_got.get(k)}, '
                       f'the config asks for {shape}')
  table = sensor.nominal_angles() if angles is None else np.load(angles)
  if np.shape(table) != (2,) + sensor.shape:
    raise ValueError(f'{angles}: angles of shape {np.shape(table)}, expected '
                     f'{(2,) + sensor.shape}')
  params = models.GeneratorParams(
      variables=jax.tree.map(jnp.asarray, got), angles=jnp.asarray(table, jnp.float32),
      model=cfg.model, sensor=sensor, latent_dim=cfg.latent_dim, ch_base=cfg.ch_base,
      ch_max=cfg.ch_max, tau=cfg.tau, eqlr='authors')
  cfg.source_checkpoint = os.path.abspath(path)
  cfg.source_step = int(ckpt.get('step', -1))
  return params, cfg
