"""The authors' released PyTorch checkpoints (kazuto1011/dusty-gan), without torch.

    params, config = dusty_jax.load_checkpoint('dusty1_0025000000.pth')   # yaml beside it
    params, config = dusty_jax.load_checkpoint('x.pth', config='config.yaml')

A ``torch.save`` file is a zip holding ``*/data.pkl`` (a pickle of the
structure) and ``*/data/N`` (the raw bytes of each tensor storage). It is
read here with a restricted unpickler: only the few globals a state dict
needs (OrderedDict, torch's tensor rebuild functions and storage types) are
known, each mapped to a numpy stand-in; any other global is refused before
anything runs, so a checkpoint from the internet cannot execute code. The
stand-ins cannot be altered by the pickle, and every tensor view (offset,
size, stride: numbers from the file) is checked to lie inside its storage,
so a forged file cannot read the process's memory either.

The generator's weights (``G_ema`` by default, as the authors' own loader;
``ema=False`` for ``G``) are mapped onto dusty_jax's parameters, whose eq-lr
constants are the authors' (``eqlr='authors'``), so the function is theirs.
The angle table is not in their checkpoint: the sensor's nominal angles are
used unless ``angles`` names a (2, H, W) ``.npy`` or their dataset's
``angles.pt``.
"""

from __future__ import annotations

import collections
import os
import pickle
import zipfile

import jax
import jax.numpy as jnp
import numpy as np
import yaml

from dusty_jax import codec, configs, models
from dusty_jax import sensor as sensor_lib
from dusty_jax.sensor import check_angles

_DTYPES = {'FloatStorage': np.float32, 'DoubleStorage': np.float64,
           'HalfStorage': np.float16, 'LongStorage': np.int64,
           'IntStorage': np.int32, 'ShortStorage': np.int16,
           'CharStorage': np.int8, 'ByteStorage': np.uint8,
           'BoolStorage': np.bool_}


class _Frozen:
  """Base of the stand-ins: a pickle's BUILD cannot set their attributes, so
  one file cannot change how the next one is read."""
  __slots__ = ()

  def __setattr__(self, name, value):
    raise pickle.UnpicklingError(f'refusing to set {name!r} on {self!r}')


class _StorageType(_Frozen):
  __slots__ = ('name', 'dtype')

  def __init__(self, name):
    object.__setattr__(self, 'name', name)
    object.__setattr__(self, 'dtype', np.dtype(_DTYPES[name]))

  def __repr__(self):
    return f'torch.{self.name}'


class _Function(_Frozen):
  __slots__ = ('name', 'fn')

  def __init__(self, name, fn):
    object.__setattr__(self, 'name', name)
    object.__setattr__(self, 'fn', fn)

  def __call__(self, *args):
    return self.fn(*args)

  def __repr__(self):
    return self.name


def _index(value, what: str) -> int:
  if not isinstance(value, int) or isinstance(value, bool) or value < 0:
    raise pickle.UnpicklingError(f'tensor {what} {value!r} is not an index')
  return value


def _rebuild_tensor(storage, offset, size, stride, *unused):
  """A copy of the tensor a (storage, offset, size, stride) view describes,
  every element checked to lie inside the storage."""
  if not isinstance(storage, np.ndarray) or storage.ndim != 1:
    raise pickle.UnpicklingError(f'tensor storage {type(storage).__name__} is not a storage')
  if not isinstance(size, tuple) or not isinstance(stride, tuple) or len(size) != len(stride):
    raise pickle.UnpicklingError(f'tensor size {size!r} and stride {stride!r} do not match')
  offset = _index(offset, 'offset')
  size = tuple(_index(n, 'size') for n in size)
  stride = tuple(_index(s, 'stride') for s in stride)
  if 0 in size:
    return np.zeros(size, storage.dtype)
  last = offset + sum((n - 1) * s for n, s in zip(size, stride))
  if last >= storage.size:
    raise pickle.UnpicklingError(
        f'tensor of size {size}, stride {stride} at offset {offset} reaches element '
        f'{last} of a storage of {storage.size}: the file is damaged or forged')
  view = np.lib.stride_tricks.as_strided(
      storage[offset:], shape=size, strides=tuple(s * storage.itemsize for s in stride),
      writeable=False)
  return np.array(view)


def _rebuild_parameter(data, *unused):
  return data


_ALLOWED = {
    ('collections', 'OrderedDict'): collections.OrderedDict,  # immutable type
    ('torch._utils', '_rebuild_tensor_v2'): _Function('_rebuild_tensor_v2', _rebuild_tensor),
    ('torch._utils', '_rebuild_parameter'): _Function('_rebuild_parameter', _rebuild_parameter),
}
_ALLOWED.update({('torch', name): _StorageType(name) for name in _DTYPES})


class _Unpickler(pickle.Unpickler):
  def __init__(self, file, zf: zipfile.ZipFile, prefix: str, source: str):
    super().__init__(file)
    self.zf, self.prefix, self.source = zf, prefix, source
    try:  # written by torch >= 2.1; older files are little-endian
      order = zf.read(f'{prefix}/byteorder').decode().strip()
    except KeyError:
      order = 'little'
    if order not in ('little', 'big'):
      raise ValueError(f'{source}: unknown byte order {order!r}')
    self.order = '<' if order == 'little' else '>'

  def find_class(self, module, name):
    try:
      return _ALLOWED[(module, name)]
    except KeyError:
      pass
    if module == 'torch' and name.endswith('Storage'):
      raise pickle.UnpicklingError(
          f'{self.source}: tensors of type torch.{name} are not supported (known: '
          f'{", ".join(sorted(_DTYPES))})')
    raise pickle.UnpicklingError(
        f'{self.source}: refusing the global {module}.{name}: a checkpoint holds '
        'tensors and dicts only, so this file is not one (or it tries to run code)')

  def persistent_load(self, pid):
    if not (isinstance(pid, tuple) and len(pid) >= 3 and pid[0] == 'storage'):
      raise pickle.UnpicklingError(f'{self.source}: unknown persistent id {pid!r}')
    storage_type, key = pid[1], pid[2]
    if not isinstance(storage_type, _StorageType):
      raise pickle.UnpicklingError(f'{self.source}: unknown storage type {storage_type!r}')
    try:
      raw = self.zf.read(f'{self.prefix}/data/{key}')
    except KeyError:
      raise pickle.UnpicklingError(f'{self.source}: storage {key!r} is missing') from None
    dtype = storage_type.dtype.newbyteorder(self.order)
    if len(raw) % dtype.itemsize:
      raise pickle.UnpicklingError(
          f'{self.source}: storage {key!r} holds {len(raw)} bytes, not a whole number '
          f'of {storage_type!r} elements')
    return np.frombuffer(raw, dtype=dtype)


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
      try:
        return _Unpickler(f, zf, prefix, path).load()
      except pickle.UnpicklingError as e:
        if str(e).startswith(path):
          raise
        raise pickle.UnpicklingError(f'{path}: {e}') from None
      except (EOFError, TypeError, ValueError, AttributeError, IndexError, KeyError) as e:
        raise pickle.UnpicklingError(
            f'{path}: a damaged checkpoint ({type(e).__name__}: {e})') from None


# ----------------------------------------------------------------------------
# Their config and key layout -> ours.
# ----------------------------------------------------------------------------

_ARCH = {v.authors_arch: v.name for v in models.VARIANTS.values()}  # their masker -> ours
_DEPTHS = (0.9, 120.0)  # the range of their datasets' configs and of our sensors


def find_config(path: str) -> str:
  """The authors' yaml of a .pth, looked for beside it and in a hydra run.

  In order: ``STEM_config.yaml``, ``PREFIX_config.yaml`` (PREFIX: the stem
  up to its first underscore, as in their release: ``dusty1_0025000000.pth``
  with ``dusty1_config.yaml``), ``config.yaml``, then ``../.hydra/config.yaml``
  (a checkpoint in its training run: ``RUN/models/checkpoint_N.pth``).
  """
  d, stem = os.path.dirname(os.path.abspath(path)), os.path.splitext(os.path.basename(path))[0]
  candidates = [os.path.join(d, f'{stem}_config.yaml'),
                os.path.join(d, f'{stem.split("_")[0]}_config.yaml'),
                os.path.join(d, 'config.yaml'),
                os.path.join(os.path.dirname(d), '.hydra', 'config.yaml')]
  candidates = list(dict.fromkeys(candidates))
  for c in candidates:
    if os.path.isfile(c):
      return c
  raise FileNotFoundError(f'{path}: no config found (looked for {candidates}); pass '
                          "config='...yaml', the authors' config of that run")


def config_from_yaml(path: str):
  """Our ConfigDict (eqlr='authors') from the authors' hydra config of a run."""
  with open(path) as f:
    y = yaml.safe_load(f)
  try:
    gen, data = y['model']['gen'], y['dataset']
    arch, shape = str(gen['arch']), tuple(int(n) for n in data['shape'])
    latent_dim, ch_base, ch_max = int(gen['in_ch']), int(gen['ch_base']), int(gen['ch_max'])
  except (KeyError, TypeError, ValueError) as e:
    raise ValueError(f'{path}: not a dusty-gan run config (no valid {e})') from None
  masker, _, backbone = arch.partition('/')
  if masker not in _ARCH or backbone != 'dcgan_eqlr':
    raise ValueError(f'{path}: unknown generator arch {arch!r}; known: '
                     f'{sorted(m + "/dcgan_eqlr" for m in _ARCH)}')
  if not y['model'].get('ring', True):
    raise ValueError(f'{path}: ring=false (reflect padding) is not supported')
  drop = float(gen.get('drop_const', codec.ALPHA))
  if drop != codec.ALPHA:
    raise ValueError(f'{path}: drop_const={drop}; dusty_jax drops to {codec.ALPHA}')
  depths = (float(data.get('min_depth', _DEPTHS[0])), float(data.get('max_depth', _DEPTHS[1])))
  if depths != _DEPTHS:
    raise ValueError(f'{path}: depth range {depths}; dusty_jax sensors have {_DEPTHS}')
  c = configs.default()
  c.model = _ARCH[masker]
  c.latent_dim, c.ch_base, c.ch_max = latent_dim, ch_base, ch_max
  c.tau = float(gen.get('tau', 1.0))
  c.eqlr = 'authors'
  preset = {(64, 256): 'kitti', (32, 256): 'mpo'}.get(shape, '')
  c.sensor.preset = preset
  if not preset:  # a sensor of that shape, with the KITTI field of view
    c.sensor.height, c.sensor.width = shape
  c.data.name = str(data.get('name', ''))
  return c


def _weights(sd, model: str, source: str) -> tuple[dict, dict]:
  """Their generator state dict -> our Flax ``params`` (numpy), and for each
  of our leaves ('head/kernel', ...) the keys and shapes it came from."""
  if not isinstance(sd, dict):
    raise ValueError(f'{source}: the generator state dict is a {type(sd).__name__}')
  variant = models.get_variant(model)
  pre = variant.authors_prefix
  dusty_keys = any(str(k).startswith('backbone.') for k in sd)
  if dusty_keys != bool(pre):
    raise ValueError(
        f'{source}: holds a {"DUSty" if dusty_keys else "baseline"} generator '
        f'({"" if dusty_keys else "no "}\'backbone.\' keys) but the config names the '
        f'{model}')
  used, origin = set(), {}

  def get(k):
    if pre + k not in sd:
      raise KeyError(f'{source}: missing key {pre + k!r} in the generator state dict')
    used.add(pre + k)
    a = sd[pre + k]
    if not isinstance(a, np.ndarray) or not np.issubdtype(a.dtype, np.floating):
      raise ValueError(f'{source}: {pre + k!r} is not a floating-point tensor')
    return a.astype(np.float32)

  def put(name, keys, arrays, value):
    origin[name] = ', '.join(f'{pre + k!r} {a.shape}' for k, a in zip(keys, arrays))
    return value

  w = get('0.0.module.weight')  # ConvTranspose2d (latent, C, h0, w0)
  p = {'proj': put('proj', ['0.0.module.weight'], [w],
                   w.transpose(0, 2, 3, 1).reshape(w.shape[0], -1) if w.ndim == 4 else w)}
  p['proj_bias'] = put('proj_bias', ['0.1.bias'], [b := get('0.1.bias')], b)
  for i in (1, 2, 3):
    k = f'{i}.1.module.weight'  # ConvTranspose2d (Cin, Cout, 4, 4)
    w = get(k)
    p[f'up{i}'] = {'kernel': put(f'up{i}/kernel', [k], [w],
                                 w.transpose(2, 3, 0, 1) if w.ndim == 4 else w)}
    p[f'up{i}_bias'] = put(f'up{i}_bias', [f'{i}.2.bias'], [b := get(f'{i}.2.bias')], b)
  # One kernel for the separate heads: depth channel first, then confidence.
  heads = [h for h, _ in variant.heads]
  keys = [f'4.heads.{h}.1.module.weight' for h in heads]
  ws = [get(k) for k in keys]
  if any(w.ndim != 4 for w in ws) or len({w.shape[0] for w in ws}) != 1:
    raise ValueError(f'{source}: head weights {[w.shape for w in ws]} do not stack')
  p['head'] = {'kernel': put('head/kernel', keys, ws,
                             np.concatenate(ws, axis=1).transpose(2, 3, 0, 1))}
  keys = [f'4.heads.{h}.1.module.bias' for h in heads]
  bs = [get(k) for k in keys]
  p['head_bias'] = put('head_bias', keys, bs, np.concatenate(bs))
  if pre + 'drop_const' in sd:  # DUSty's buffer: the value dropped points take
    used.add(pre + 'drop_const')
  if 'drop_const' in sd:
    used.add('drop_const')
    if float(np.asarray(sd['drop_const'])) != codec.ALPHA:
      raise ValueError(f'{source}: drop_const {float(np.asarray(sd["drop_const"]))}; '
                       f'dusty_jax drops to {codec.ALPHA}')
  extra = sorted(set(sd) - used)
  if extra:
    raise ValueError(f'{source}: unexpected keys in the generator state dict: {extra} '
                     '(a different architecture than the config names?)')
  return p, origin


def read_angles(path: str, sensor) -> np.ndarray:
  """A (2, H, W) elevation/azimuth table (radians) from ``.npy`` or the
  authors' ``angles.pt`` (their dataset root; pitch, yaw at the native
  resolution), the latter resized as their LiDAR class does (bilinear,
  half-pixel centres, as ``F.interpolate(mode='bilinear')``)."""
  if path.endswith('.npy'):
    table = np.load(path, allow_pickle=False)
  else:
    table = read_torch_checkpoint(path)
    if not isinstance(table, np.ndarray):
      raise ValueError(f'{path}: holds a {type(table).__name__}, not an angle table')
    if table.ndim == 3 and table.shape[0] == 2:
      table = _resize_bilinear(table.astype(np.float64), sensor.shape)
  check_angles(table, sensor.shape, f'{path}: ', finite=True)
  return np.asarray(table, np.float32)


def _resize_bilinear(a: np.ndarray, shape) -> np.ndarray:
  """(C, h, w) -> (C, H, W) as PyTorch's bilinear interpolate (align_corners=False)."""
  def taps(n_in, n_out):
    src = np.maximum((np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5, 0.0)
    i0 = np.minimum(np.floor(src).astype(int), n_in - 1)
    i1 = np.minimum(i0 + 1, n_in - 1)
    return i0, i1, src - i0

  r0, r1, fr = taps(a.shape[1], shape[0])
  c0, c1, fc = taps(a.shape[2], shape[1])
  rows = a[:, r0] * (1 - fr)[:, None] + a[:, r1] * fr[:, None]
  return rows[:, :, c0] * (1 - fc) + rows[:, :, c1] * fc


def load(path: str, config: str | None = None, ema: bool = True,
         angles: str | None = None):
  """(generator fields, config) of an authors' ``.pth`` checkpoint
  (``dusty_jax.load_checkpoint`` makes the GeneratorParams).

  Args:
    path: their checkpoint (``torch.save`` of a dict with 'G_ema' and 'G').
    config: their yaml of that run; by default found by :func:`find_config`.
    ema: take 'G_ema' (as their loader does); False: 'G'.
    angles: a (2, H, W) ``.npy`` or their dataset's ``angles.pt``; by
      default the sensor's nominal angles.

  Returns:
    A dict of GeneratorParams' fields (variables, angles, sensor,
    settings) and a ConfigDict like a dusty_jax run's, with
    ``source_checkpoint`` and ``source_step`` added.
  """
  ckpt = read_torch_checkpoint(path)
  cfg = config_from_yaml(config or find_config(path))
  key = 'G_ema' if ema else 'G'
  if not isinstance(ckpt, dict) or key not in ckpt:
    raise KeyError(f'{path}: no {key!r} in the checkpoint (keys: '
                   f'{sorted(ckpt) if isinstance(ckpt, dict) else type(ckpt).__name__})')
  sensor = sensor_lib.from_config(cfg.sensor)
  settings = models.ModelSettings(model=cfg.model, latent_dim=cfg.latent_dim,
                                  ch_base=cfg.ch_base, ch_max=cfg.ch_max,
                                  eqlr='authors', tau=float(cfg.tau))
  module = settings.generator(sensor)
  want = jax.eval_shape(module.init, jax.random.key(0), jnp.zeros((1, cfg.latent_dim)))
  weights, origin = _weights(ckpt[key], cfg.model, f'{path} [{key!r}]')
  got = {'params': weights}
  flat_got = {'/'.join(str(k.key) for k in p): v.shape
              for p, v in jax.tree_util.tree_leaves_with_path(got)}
  for p, v in jax.tree_util.tree_leaves_with_path(want):
    name = '/'.join(str(k.key) for k in p[1:])
    if flat_got.get('params/' + name) != v.shape:
      raise ValueError(
          f'{path}: {key} {origin.get(name, "(none)")} give {name} the shape '
          f'{flat_got.get("params/" + name)}; the config ({cfg.model}, latent '
          f'{cfg.latent_dim}, channels {cfg.ch_base}..{cfg.ch_max}, sensor '
          f'{sensor.shape}) asks for {v.shape}')
  table = sensor.nominal_angles() if angles is None else read_angles(angles, sensor)
  cfg.source_checkpoint = os.path.abspath(path)
  cfg.source_step = int(ckpt.get('step', -1))
  generator = dict(variables=jax.tree.map(jnp.asarray, got),
                   angles=jnp.asarray(table, jnp.float32), sensor=sensor, settings=settings)
  return generator, cfg
