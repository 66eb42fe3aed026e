"""Drop levels per (ring, depth) cell (dusty_jax/levels.py): the cells, the
real keep rates, the generator's offsets, the fit and where a run keeps it."""

import os
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dusty_jax import checkpoint, codec, configs, evaluation, generator, levels, sampling, trainer
from dusty_jax.codec import ALPHA
from dusty_jax.models import ModelSettings
from dusty_jax.sensor import tiny_sensor
from train_helpers import tiny_config


def _neighbour_bins_loop(x, keep, sensor, edges):
  """neighbour_depth_bin by explicit loops over pixels and their window."""
  b, h, w = x.shape
  codes = np.asarray([float(codec.encode(np.float32(e), sensor)) for e in edges])
  out = np.zeros((b, h, w), np.int64)
  for n in range(b):
    for r in range(h):
      for c in range(w):
        vals = [x[n, rr, cc % w] for rr in range(r - 1, r + 2) for cc in range(c - 2, c + 3)
                if 0 <= rr < h and (rr, cc) != (r, c) and keep[n, rr, cc % w]]
        out[n, r, c] = 0 if not vals else 1 + int(np.sum(np.mean(vals) <= codes))
  return out


def _scans(sensor, n=3, seed=5, drop=0.4):
  """Metric depth growing along each ring (2 to 80 m, so every bin is
  reached), ``drop`` of it 0."""
  rng = np.random.default_rng(seed)
  h, w = sensor.shape
  depth = (np.geomspace(2.0, 80.0, w) * rng.uniform(0.9, 1.1, (n, h, w))).astype(np.float32)
  depth[rng.uniform(size=depth.shape) < drop] = 0.0
  return depth


def test_neighbour_depth_bin_against_loops():
  sensor = tiny_sensor(6, 12)
  depth = _scans(sensor)
  keep = depth > 0
  keep[0, :3] = False  # a pixel whose neighbours all dropped: bin 0
  x = np.where(keep, np.asarray(codec.encode(depth, sensor)), ALPHA).astype(np.float32)
  edges = (5.0, 20.0, 40.0)
  got = np.asarray(levels.neighbour_depth_bin(jnp.asarray(x), jnp.asarray(keep), sensor, edges))
  want = _neighbour_bins_loop(x, keep, sensor, edges)
  np.testing.assert_array_equal(got, want)
  assert (want == 0).any() and len(np.unique(want)) == len(edges) + 2
  # The pixel itself never counts: flipping it leaves its own bin unchanged.
  flipped = keep.copy()
  flipped[1, 3, 5] = ~flipped[1, 3, 5]
  again = levels.neighbour_depth_bin(jnp.asarray(x), jnp.asarray(flipped), sensor, edges)
  assert int(again[1, 3, 5]) == int(got[1, 3, 5])


def test_observed_keep_against_loops():
  sensor = tiny_sensor(6, 12)
  depth = _scans(sensor, n=4)
  keep = depth > 0
  x = np.where(keep, np.asarray(codec.encode(depth, sensor)), ALPHA)
  bins = _neighbour_bins_loop(x, keep, sensor, levels.EDGES)
  index = np.arange(sensor.shape[0])[None, :, None] * levels.BINS + bins
  table, ring = levels.observed_keep(index, keep, sensor.shape[0])
  np.testing.assert_allclose(ring, keep.mean(axis=(0, 2)))
  for r in range(sensor.shape[0]):
    for b in range(levels.BINS):
      cell = bins[:, r] == b
      want = (keep[:, r][cell].sum() + levels.PSEUDO_COUNT * ring[r]) / (
          cell.sum() + levels.PSEUDO_COUNT)
      assert table[r, b] == pytest.approx(want)


def _generator(model='dusty1', depth_levels=False, ring_bias=False, sensor=None):
  sensor = sensor or tiny_sensor(16, 64)
  settings = ModelSettings(model=model, latent_dim=16, ch_base=8, ch_max=16,
                           ring_bias=ring_bias, depth_levels=depth_levels)
  module = settings.generator(sensor)
  variables = module.init(jax.random.key(0), jnp.zeros((1, 16)))
  angles = jnp.asarray(sensor.nominal_angles(), jnp.float32)
  return generator.GeneratorParams(variables=variables, angles=angles, sensor=sensor,
                                   settings=settings)


@pytest.mark.parametrize('model', ['dusty1', 'dusty2'])
def test_the_generator_adds_the_offset_of_each_pixels_cell(model):
  plain = _generator(model)
  table = np.random.default_rng(1).normal(size=(16, levels.BINS)).astype(np.float32)
  leveled = levels.with_levels(plain, table)
  assert leveled.settings.depth_levels
  z = jax.random.normal(jax.random.key(2), (3, 16))
  a = np.asarray(plain.module().apply(plain.variables, z))
  b = np.asarray(leveled.module().apply(leveled.variables, z))
  x = np.tanh(a[..., 0])
  bins = _neighbour_bins_loop(x, x > ALPHA, plain.sensor, levels.EDGES)
  want = a.copy()
  want[..., 1] += table[np.arange(16)[None, :, None], bins]
  np.testing.assert_allclose(b, want, rtol=1e-5, atol=1e-5)
  # Only the pixel logit moves: depth and DUSty-II's image logit stay.
  np.testing.assert_array_equal(b[..., 0], a[..., 0])
  if model == 'dusty2':
    np.testing.assert_array_equal(b[..., 2], a[..., 2])


def test_a_model_without_measurability_has_no_levels():
  with pytest.raises(ValueError, match='depth_levels'):
    _generator('baseline', depth_levels=True)
  with pytest.raises(ValueError, match='no measurability'):
    levels.calibrate(_generator('baseline'), np.ones((2, 16, 64), np.float32),
                     np.zeros((2, 16), np.float32))


def _open(params):
  """DUSty-II's image logit opened, so its scans all return (a random start
  gates about half of them, and no offset of the pixel logit reaches those)."""
  if params.variant.logit(jnp.zeros((1, 1, 1, 3))).ndim < 4:
    return params
  p = dict(params.variables['params'])
  p['head_bias'] = p['head_bias'].at[2].set(5.0)
  return params.replace(variables={**params.variables, 'params': p})


def _keep_of(params, z):
  """(expected keep per pixel, x_tilde, raw) of latents z."""
  raw = params.module().apply(params.variables, z)
  v = params.variant
  x = v.decode_inv_depth(raw)
  return np.asarray(v.measurability(v.logit(raw)) * (x > ALPHA)), x, np.asarray(raw)


def _ring_and_depth_scans(sensor, n=8):
  """Scans whose keep rate rises with the ring (30% to 90%) and falls with
  the range: each (ring, depth) cell has its own rate."""
  depth = _scans(sensor, n=n, drop=0.0)
  rng = np.random.default_rng(3)
  rate = np.linspace(0.3, 0.9, sensor.shape[0])[None, :, None] * (1.2 - depth / 100.0)
  depth[rng.uniform(size=depth.shape) > rate] = 0.0
  return depth


@pytest.mark.parametrize('model, ring_bias', [('dusty1', True), ('dusty2', False)])
def test_calibrate_fits_each_cell_of_the_inversions(model, ring_bias):
  params = _open(_generator(model, ring_bias=ring_bias))
  sensor = params.sensor
  depth = _ring_and_depth_scans(sensor, n=24)
  z = jax.random.normal(jax.random.key(4), (24, 16))  # stand-ins for the scans' inversions
  fitted = levels.calibrate(params, depth, z)
  keep, x, after = _keep_of(fitted, z)
  # The cells are those of the latents' x_tilde; the targets the scans' keep there.
  index = np.asarray(levels.of_x_tilde(x, sensor)).ravel()
  table, _ = levels.observed_keep(index, codec.valid_depth(depth, sensor), sensor.shape[0])
  returns = np.bincount(index, np.asarray(x > ALPHA).ravel(), minlength=table.size)
  count = np.bincount(index, minlength=table.size)
  got = np.bincount(index, keep.ravel(), minlength=table.size) / np.maximum(count, 1)
  fitted_cells = returns >= levels.MIN_PIXELS
  assert 10 <= fitted_cells.sum() < table.size  # some cells take their ring's mean
  np.testing.assert_allclose(got[fitted_cells], table.ravel()[fitted_cells], atol=2e-3)
  offsets = np.asarray(fitted.variables['params']['depth_levels'])
  for r in range(sensor.shape[0]):  # the others: their ring's mean, weighted by returns
    own = fitted_cells.reshape(offsets.shape)[r]
    if own.any() and not own.all():
      w = returns.reshape(offsets.shape)[r] * own
      np.testing.assert_allclose(offsets[r][~own], (offsets[r] * w).sum() / w.sum(), rtol=1e-5)
  # Only the pixel logit moved; a model with other levels refits to the same.
  before = np.asarray(params.module().apply(params.variables, z))
  np.testing.assert_array_equal(after[..., 0], before[..., 0])
  other = levels.with_levels(params, np.random.default_rng(1).normal(
      size=offsets.shape) * 3)
  again = levels.calibrate(other, depth, z)
  np.testing.assert_allclose(again.variables['params']['depth_levels'], offsets, atol=1e-3)
  with pytest.raises(ValueError, match=r'latents of shape \(3, 16\) for 24 scans'):
    levels.calibrate(params, depth, z[:3])
  with pytest.raises(ValueError, match=r'scans of shape \(24, 16, 32\)'):
    levels.calibrate(params, depth[..., :32], z)


@pytest.mark.slow
def test_fit_levels_matches_the_inversions_it_fits_to():
  """evaluation.fit_levels, round trip: invert the same scans with the
  leveled generator, and each fitted cell keeps what the scans keep there
  (the levels move no x_tilde and the inversion ignores the measurability)."""
  params = _generator('dusty1')
  depth = _ring_and_depth_scans(params.sensor, n=12)
  fitted = evaluation.fit_levels(params, depth, num=10, num_steps=3, batch=4)
  assert fitted.settings.depth_levels
  (_, d, _, _, res), = evaluation.restore_batches(fitted, depth[:10], num_steps=3, batch=10)
  x = res['inv_depth']
  index = np.asarray(levels.of_x_tilde(x, params.sensor)).ravel()
  table, _ = levels.observed_keep(index, codec.valid_depth(d, params.sensor), 16)
  keep = (res['measurability'] * (x > ALPHA)).ravel()
  got = np.bincount(index, keep, minlength=table.size) / np.maximum(
      np.bincount(index, minlength=table.size), 1)
  fitted_cells = np.bincount(index, (x > ALPHA).ravel(), minlength=table.size) >= levels.MIN_PIXELS
  assert fitted_cells.sum() >= 5
  np.testing.assert_allclose(got[fitted_cells], table.ravel()[fitted_cells], atol=2e-3)
  with pytest.raises(ValueError, match='no training scans'):
    evaluation.fit_levels(params, depth[:0])


@pytest.mark.slow
def test_a_run_applies_its_levels_at_their_step_only(smoke_run, tmp_path):
  _, workdir, _ = smoke_run
  run = str(tmp_path / 'run')
  shutil.copytree(workdir, run)
  plain, _ = generator.load(run, log=lambda m: None)
  table = np.random.default_rng(0).normal(size=(plain.sensor.shape[0], levels.BINS))
  steps = sorted(int(s) for s in os.listdir(os.path.join(run, 'checkpoints')) if s.isdigit())
  levels.save(run, table, steps[-1])
  leveled, _ = generator.load(run, log=lambda m: None)
  assert leveled.settings.depth_levels and not plain.settings.depth_levels
  np.testing.assert_allclose(leveled.variables['params']['depth_levels'], table, rtol=1e-6)
  said = []
  older, _ = generator.load(run, step=steps[0], log=said.append)
  assert not older.settings.depth_levels
  assert any(f'fits step {steps[-1]}' in m and f'step {steps[0]}' in m for m in said)
  # An exported file carries them; a damaged one is refused by name.
  path = generator.export(leveled, str(tmp_path / 'g.npz'))
  again = generator.load_file(path)
  assert again.settings.depth_levels
  np.testing.assert_array_equal(np.asarray(sampling.sample(again, jax.random.key(1), 2)['scan']),
                                np.asarray(sampling.sample(leveled, jax.random.key(1), 2)['scan']))
  with open(os.path.join(run, levels.FILE), 'wb') as f:
    f.write(b'not a npz')
  with pytest.raises(ValueError, match=levels.FILE):
    generator.load(run, log=lambda m: None)


@pytest.mark.slow
def test_training_with_depth_levels_ends_with_them_fitted(tmp_path):
  config = tiny_config(num_steps=2, checkpoint_every=2, log_every=1, image_every=2)
  config.data.cache = str(tmp_path / 'cache')
  config.data.num_synthetic = 24
  config.drops.depth_levels = True
  configs.validate(config)
  said = []
  trainer.train_and_evaluate(config, str(tmp_path / 'run'), log=said.append)
  fitted = levels.load(str(tmp_path / 'run'))
  assert fitted is not None and fitted[1] == 2
  assert any(levels.FILE in m for m in said)
  params, _ = generator.load(str(tmp_path / 'run'), log=lambda m: None)
  assert params.settings.depth_levels
  # The training itself did not change: its checkpoint holds no levels.
  ema, _ = checkpoint.restore_item(str(tmp_path / 'run' / 'checkpoints'), 'ema_params')
  assert 'depth_levels' not in ema['params'] and 'ring_bias' not in ema['params']


@pytest.mark.slow
def test_a_run_started_from_a_leveled_model_keeps_its_levels_apart(tmp_path):
  """trainer.init_run (convert, the study's --from-pretrained): the levels go
  to the run's levels file at step 0, the checkpoint holds the weights."""
  config = tiny_config()
  params = levels.with_levels(
      _generator(sensor=tiny_sensor(config.sensor.height, config.sensor.width)),
      np.random.default_rng(2).normal(size=(config.sensor.height, levels.BINS)))
  config.latent_dim, config.ch_base, config.ch_max = 16, 8, 16
  trainer.init_run(str(tmp_path / 'run'), config, params)
  loaded, _ = generator.load(str(tmp_path / 'run'), log=lambda m: None)
  np.testing.assert_allclose(loaded.variables['params']['depth_levels'],
                             params.variables['params']['depth_levels'])
  z = jax.random.normal(jax.random.key(0), (2, 16))
  np.testing.assert_allclose(np.asarray(loaded.module().apply(loaded.variables, z)),
                             np.asarray(params.module().apply(params.variables, z)), atol=1e-6)


def test_depth_levels_need_a_measurability():
  c = tiny_config()
  c.model = 'baseline'
  c.drops.depth_levels = True
  with pytest.raises(configs.ConfigError, match='drops.depth_levels'):
    configs.validate(c)
