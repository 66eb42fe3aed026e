"""The point-drop mechanisms beyond the paper (dusty_jax/drops.py, config
``drops``), each against what it should compute."""

import dataclasses
import importlib.util
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dusty_jax import codec, configs, drops, generator, parallel, pretrained, trainer
from dusty_jax.codec import ALPHA
from dusty_jax.sensor import tiny_sensor
from train_helpers import STUDY, tiny_config


def _scans_and_keep(b=8, h=16, w=64, seed=0, rate=0.3):
  rng = np.random.default_rng(seed)
  keep = (rng.uniform(size=(b, h, w)) > rate).astype(np.float32)
  x = np.where(keep > 0, rng.uniform(-0.9, 1, (b, h, w)), ALPHA).astype(np.float32)
  return jnp.asarray(x), jnp.asarray(keep)


def _setup(init=True, ring_keep=None, **options):
  c = tiny_config()
  c.drops.update(options)
  configs.validate(c)
  sensor = tiny_sensor(c.sensor.height, c.sensor.width)
  setup = trainer.make_setup(c, sensor)
  return c, setup, (trainer.init_state(setup, jax.random.key(0), ring_keep)
                    if init else None)


def test_cell_rate_penalty_against_numpy():
  rng = np.random.default_rng(6)
  keep = rng.uniform(size=(4, 5, 7)).astype(np.float32)
  real = (rng.uniform(size=keep.shape) > 0.3).astype(np.float32)
  cells, real_cells = rng.integers(0, 6, keep.shape), rng.integers(0, 5, keep.shape)
  num = 7  # cell 5 has no reals, cell 6 no pixel at all: both weigh 0
  total, weight = 0.0, 0.0
  for c in range(num):
    f, r = cells == c, real_cells == c
    if f.any() and r.any():
      total += f.sum() * (keep[f].mean() - real[r].mean()) ** 2
      weight += f.sum()
  got = drops.cell_rate_penalty(jnp.asarray(keep), jnp.asarray(real),
                                  jnp.asarray(cells), jnp.asarray(real_cells), num)
  assert float(got) == pytest.approx(total / weight, rel=1e-5)
  # Each generated pixel is pushed towards its own cell's real rate.
  g = np.asarray(jax.grad(drops.cell_rate_penalty)(
      jnp.asarray(keep), jnp.asarray(real), jnp.asarray(cells), jnp.asarray(real_cells), num))
  for c in range(5):
    f = cells == c
    assert np.all(np.sign(g[f]) == np.sign(keep[f].mean() - real[real_cells == c].mean()))
  np.testing.assert_array_equal(g[cells == 5], 0.0)
  # Its size: 2 (cell gap) / (the weighted pixels), the same for every pixel
  # of a cell; the real masks get none.
  c0 = cells == 0
  gap0 = keep[c0].mean() - real[real_cells == 0].mean()
  np.testing.assert_allclose(g[c0], 2 * gap0 / weight, rtol=1e-4)
  g_real = jax.grad(drops.cell_rate_penalty, argnums=1)(
      jnp.asarray(keep), jnp.asarray(real), jnp.asarray(cells), jnp.asarray(real_cells), num)
  assert float(jnp.abs(g_real).max()) == 0.0


def test_ring_depth_rate_teaches_drops_by_depth_within_a_ring():
  """Real scans keep every near pixel and half the far ones, and each ring
  holds both (columns 0-15 near, 16-31 far). The generated scans keep 75%
  everywhere: the right rate for each ring, so the per-ring term is 0, but
  the ring_depth term pulls near pixels up and far ones down."""
  sensor = tiny_sensor(4, 32)
  near, far = (float(codec.encode(np.float32(d), sensor)) for d in (3.0, 50.0))
  r, c = np.meshgrid(np.arange(4), np.arange(32), indexing='ij')
  x = np.broadcast_to(np.where(c < 16, near, far), (2, 4, 32)).astype(np.float32)
  real_keep = np.broadcast_to((c < 16) | ((r + c) % 2 == 0), x.shape).astype(np.float32)
  fake_keep = jnp.asarray(np.broadcast_to((r + c) % 4 != 0, x.shape), jnp.float32)
  real = (jnp.asarray(np.where(real_keep > 0, x, ALPHA)), jnp.asarray(real_keep))
  fake_scan = jnp.where(fake_keep > 0, jnp.asarray(x), ALPHA)
  penalty = lambda k: drops.ring_depth_rate_penalty(sensor, (fake_scan, k), real)
  assert float(penalty(fake_keep)) > 0
  g = np.asarray(jax.grad(penalty)(fake_keep))
  # Away from the seams (the window reaches 2 columns): near pixels are
  # pushed to keep (the penalty falls as they rise), far ones to drop.
  assert (g[..., 2:14] < 0).all() and (g[..., 18:30] > 0).all()
  ring = np.asarray(fake_keep).mean(axis=(0, 2)) - real_keep.mean(axis=(0, 2))
  assert np.abs(ring).max() == 0.0  # the per-ring rates already agree
  # A scene at one depth falls in the bin that depth names.
  for d, want in ((3.0, 1), (12.0, 3), (50.0, 7), (100.0, 8)):
    x1 = jnp.full((1, 4, 32), float(codec.encode(np.float32(d), sensor)))
    bins = drops.neighbour_depth_bin(x1, jnp.ones_like(x1), sensor)
    assert (np.asarray(bins) == want).all(), (d, np.unique(bins))


@pytest.mark.slow
def test_rate_head_only_trains_the_head_and_leaves_the_trunk():
  _, setup, state = _setup(ring_keep=np.linspace(0.3, 0.9, 16), rate_weight=1.0,
                           rate_head_only=True, ring_bias=True)
  gen, variant = setup.generator, setup.settings.variant
  z = jax.random.normal(jax.random.key(2), (4, setup.settings.latent_dim))
  raw, raw_head = gen.apply(state.g_params, z, detached_head=True)
  np.testing.assert_array_equal(raw, raw_head)
  np.testing.assert_array_equal(raw, gen.apply(state.g_params, z))
  real = jnp.asarray(_scans_and_keep(b=4, rate=0.5)[1])

  def rate(p, detached):
    out = gen.apply(p, z, detached_head=True)[1 if detached else 0]
    keep = variant.measurability(variant.logit(out))  # each ring's rate, pulled to real's
    return jnp.mean(jnp.square(keep.mean(axis=(0, 2)) - real.mean(axis=(0, 2))))
  for detached in (True, False):
    g = jax.grad(rate)(state.g_params, detached)['params']
    head = {'head', 'head_bias', 'ring_bias'}
    assert all(float(jnp.abs(l).max()) > 0 for k in head for l in jax.tree.leaves(g[k]))
    trunk = max(float(jnp.abs(l).max()) for k in g if k not in head
                for l in jax.tree.leaves(g[k]))
    assert (trunk == 0.0) if detached else (trunk > 0.0)


@pytest.mark.slow
@pytest.mark.parametrize('model', ['dusty1', 'dusty2'])
def test_mask_detached_keeps_every_mask_gradient_off_the_trunk(model):
  kw = dict(ring_keep=np.linspace(0.3, 0.9, 16), ring_bias=True, mask_bias=1.0)
  c, setup, state = _setup(**kw)
  c.model = model
  setup = trainer.make_setup(c, setup.sensor)
  state = trainer.init_state(setup, jax.random.key(0), kw['ring_keep'])
  detached = setup.replace(drops=dataclasses.replace(setup.drops, mask_detached=True))
  z = jax.random.normal(jax.random.key(2), (4, setup.settings.latent_dim))
  keys = jax.random.split(jax.random.key(3), 4)
  weights = jax.random.normal(jax.random.key(4), (4,) + setup.sensor.shape)
  # The same scans, masks and depth with and without the option.
  for k in ('scan', 'mask', 'inv_depth', 'logit'):
    np.testing.assert_array_equal(trainer.fake_scans(setup, state.g_params, z, keys)[k],
                                  trainer.fake_scans(detached, state.g_params, z, keys)[k])
  head = {'head', 'head_bias', 'ring_bias'}
  def grads(s, what):
    return jax.grad(lambda p: jnp.sum(
        weights * trainer.fake_scans(s, p, z, keys)[what]))(state.g_params)['params']
  def trunk(g):
    return max(float(jnp.abs(l).max()) for k in g if k not in head for l in jax.tree.leaves(g[k]))
  # The mask (straight-through to the measurability) reaches the trunk only
  # without the option; with it, the head's mask kernel still learns.
  assert trunk(grads(setup, 'mask')) > 0
  g = grads(detached, 'mask')
  assert trunk(g) == 0.0
  assert float(jnp.abs(g['head']['kernel'][..., 1:]).max()) > 0
  assert float(jnp.abs(g['ring_bias']).max()) > 0
  # x_tilde trains the trunk as before, to the bit.
  a, b = grads(setup, 'inv_depth'), grads(detached, 'inv_depth')
  jax.tree.map(np.testing.assert_array_equal, a, b)


def test_mask_bias_sets_the_initial_keep_rate():
  _, setup, state = _setup(mask_bias=2.0)
  np.testing.assert_array_equal(state.g_params['params']['head_bias'], [0.0, 2.0])
  z = jax.random.normal(jax.random.key(2), (32, setup.settings.latent_dim))
  keys = jax.random.split(jax.random.key(3), 32)
  masks = jax.jit(lambda p: trainer.fake_scans(setup, p, z, keys)['mask'])
  keep = masks(state.g_params)
  _, _, state0 = _setup()
  keep0 = masks(state0.g_params)
  # The keep rate rises from about one half towards sigmoid(2) = 0.88.
  assert float(keep0.mean()) == pytest.approx(0.5, abs=0.08)
  assert float(keep.mean()) > 0.75


def test_ring_keep_rate_counts_returns_per_row(tiny):
  rng = np.random.default_rng(5)
  depth = rng.uniform(2, 50, (40,) + tiny.shape).astype(np.float32)
  depth[rng.uniform(size=depth.shape) < np.linspace(0.05, 0.9, tiny.shape[0])[:, None]] = 0
  depth[0, 3, :5] = tiny.max_depth + 10  # out of range: not a return.
  want = ((depth[:30] > 0) & (depth[:30] <= tiny.max_depth)).mean(axis=(0, 2))
  np.testing.assert_allclose(drops.ring_keep_rate(depth, tiny, num=30), want)
  with pytest.raises(ValueError, match='no scans'):
    drops.ring_keep_rate(depth[:0], tiny)


def test_ring_bias_starts_each_ring_at_the_data_keep_rate():
  rows = 16  # the tiny config's sensor
  keep = np.linspace(0.3, 0.95, rows)
  keep[2] = 0.0  # a ring that never returns starts at the clip, finitely.
  _, setup, state = _setup(ring_keep=keep, ring_bias=True, mask_bias=1.0)
  p = state.g_params['params']
  start = np.asarray(p['ring_bias']) + float(p['head_bias'][1])
  clipped = np.clip(keep, drops.RING_KEEP_CLIP, 1 - drops.RING_KEEP_CLIP)
  np.testing.assert_allclose(start, np.log(clipped / (1 - clipped)), rtol=1e-5, atol=1e-5)
  # The generated keep rate of each ring follows (the head's own random
  # output at init moves it by a little).
  z = jax.random.normal(jax.random.key(2), (64, setup.settings.latent_dim))
  keys = jax.random.split(jax.random.key(3), 64)
  mask = jax.jit(lambda q: trainer.fake_scans(setup, q, z, keys)['mask'])(state.g_params)
  got = np.asarray(mask).mean(axis=(0, 2))
  assert np.corrcoef(got, clipped)[0, 1] > 0.95
  assert np.abs(got - clipped).max() < 0.12
  # Without the option G has no such variables, as the authors' G.
  assert 'ring_bias' not in _setup()[2].g_params['params']
  with pytest.raises(ValueError, match='16 rings'):
    drops.set_ring_bias(state.g_params, keep[:4])


def test_a_step_with_the_rate_options_moves_each_ring_to_its_rate():
  # (The rate term's cells nest in the rings.)
  c, setup, state = _setup(ring_keep=np.full(16, 0.5), mask_bias=1.4, rate_weight=1e4,
                           rate_head_only=True, ring_bias=True)
  mesh = parallel.data_mesh(jax.devices()[:1])
  step = parallel.data_parallel(trainer.step_fn(setup), mesh)
  state = parallel.replicate(state, mesh)
  # Real scans: the top half of the rings keeps 90%, the bottom half 10%.
  x = np.array(_scans_and_keep(b=c.batch_size, rate=0.0)[0])
  rng = np.random.default_rng(1)
  x[rng.uniform(size=x.shape) > np.where(np.arange(16) < 8, 0.9, 0.1)[:, None]] = ALPHA
  before = jax.tree.map(np.asarray, parallel.to_host(state.g_params))['params']
  state, m = step(state, parallel.shard_batch(x, mesh), jax.random.key(1))
  m = parallel.to_host(m)
  assert all(np.isfinite(float(v)) for v in m.values())
  after = parallel.to_host(state.g_params)['params']
  assert not np.allclose(np.asarray(after['head_bias']), before['head_bias'])
  # The rate term (weighted to dominate here) moves each ring's offset
  # towards that ring's real rate, from 0.5 everywhere.
  moved = np.asarray(after['ring_bias']) - before['ring_bias']
  assert (moved[:8] > 0).all() and (moved[8:] < 0).all()


@pytest.mark.parametrize('field,value', [('rate_weight', -1.0), ('rate_head_only', True),
                                         ('dip_weight', -1.0)])
def test_bad_drop_options_name_the_field(field, value):
  c = tiny_config()
  c.drops[field] = value  # rate_head_only without a rate term
  with pytest.raises(configs.ConfigError, match=f'drops.{field}'):
    configs.validate(c)


@pytest.mark.parametrize('field,value', [('rate_weight', 1.0), ('ring_bias', True),
                                         ('mask_detached', True), ('mask_bias', 1.0),
                                         ('depth_levels', True)])
def test_baseline_refuses_mask_options(field, value):
  c = tiny_config(model='baseline')
  c.drops[field] = value
  with pytest.raises(configs.ConfigError, match=f'drops.{field}.*no measurability'):
    configs.validate(c)


@pytest.mark.parametrize('name, model, preset', [('sim-dusty1', 'dusty1', 'levels'),
                                                 ('sim-dusty2', 'dusty2', 'dips')])
def test_the_presets_are_what_the_shipped_models_trained_with(name, model, preset):
  """Each shipped model records its drops options (generator.export's
  ``training``) and the experiments/ config that trained it: that config
  exists, gives the model's preset, and the recorded options are its
  drops group as this version writes it."""
  training = pretrained.describe(name)['training']
  here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  path, _, arg = training['config'].partition(':')
  assert os.path.isfile(os.path.join(here, path)), training['config']
  spec = importlib.util.spec_from_file_location('shipped_config', os.path.join(here, path))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  config = module.get_config(arg) if arg else module.get_config()
  assert config.model == model
  assert config.drops.to_dict() == STUDY['study'](model, preset).drops.to_dict()
  assert training['drops'] == config.drops.to_dict()


def test_a_generator_description_of_the_research_era_is_one_line(tiny, tmp_path):
  """A generator.json whose settings hold an option since removed (as those
  of the research era do) is refused, naming it and the last version that
  reads it; this version's own loads."""
  settings = configs.model_settings(tiny_config())
  generator.save_spec(str(tmp_path), tiny, settings, tiny.nominal_angles())
  assert generator.read_spec(str(tmp_path))[1] == settings
  path = tmp_path / generator.SPEC_FILE
  d = json.loads(path.read_text())
  d['settings']['range_slope'] = False
  path.write_text(json.dumps(d))
  with pytest.raises(configs.ConfigError, match=(
      r'settings\.range_slope is no model setting of this version; written by a '
      r'research-era dusty_jax; dusty_jax 0\.1\.0 is the last version that reads it$')):
    generator.read_spec(str(tmp_path))


def test_only_the_ring_bias_changes_the_architecture():
  a, b = tiny_config(), tiny_config()
  b.drops.update(STUDY['DIPS'], ring_bias=False)
  assert configs.architecture_diff(a, b) == {}
  b.drops.ring_bias = True
  assert 'drops' in configs.architecture_diff(a, b)


@pytest.mark.slow
def test_the_dip_term_fills_the_generated_dips():
  """One G step with dip_weight weighted to dominate fills the dips among
  the generated returns, where the same step without it does not."""
  gaps = {}
  for weight in (0.0, 1e3):
    c, setup, state = _setup(mask_detached=True, rate_weight=1.0, rate_head_only=True,
                             dip_weight=weight)
    mesh = parallel.data_mesh(jax.devices()[:1])
    step = parallel.data_parallel(trainer.step_fn(setup), mesh)
    z = jax.random.normal(jax.random.key(2), (c.batch_size, setup.settings.latent_dim))
    keys = jax.random.split(jax.random.key(3), c.batch_size)
    real = np.where(np.asarray(_scans_and_keep(b=c.batch_size)[1]) > 0, 0.8,
                    ALPHA).astype(np.float32)
    def gap(g_params):
      scan = trainer.fake_scans(setup, g_params, z, keys)['scan']
      return float(drops.dip_penalty(scan))
    before = gap(state.g_params)
    state, m = step(parallel.replicate(state, mesh), parallel.shard_batch(real, mesh),
                    jax.random.key(1))
    m = parallel.to_host(m)
    gaps[weight] = gap(parallel.to_host(state.g_params)) - before
  # Each falls in one step by more than 1% of where it started, and by that
  # much more than without the term.
  assert gaps[1e3] < -before / 100 and gaps[1e3] < gaps[0.0] - before / 100, (before, gaps)


def test_dips_against_loops():
  rng = np.random.default_rng(6)
  x = rng.uniform(-0.9, 1, (3, 5, 12)).astype(np.float32)
  x[rng.uniform(size=x.shape) < 0.2] = ALPHA
  x[0, 0, 0] = -2.0  # a drop at another drop constant is a drop too
  depth, counted = (np.asarray(a) for a in drops.dips(jnp.asarray(x)))
  want_d, want_c = np.zeros(x.shape), np.zeros(x.shape, bool)
  for n, r, c in np.ndindex(*x.shape):
    trio = [x[n, r, (c + k) % 12] for k in (-1, 0, 1)]  # the ring wraps around
    if min(trio) > ALPHA:
      want_c[n, r, c] = True
      want_d[n, r, c] = max(0.0, min(trio[0], trio[2]) - trio[1] - drops.DIP)
  np.testing.assert_array_equal(counted, want_c)
  np.testing.assert_allclose(depth, want_d, rtol=0, atol=1e-6)
  assert 0 < (want_d > 0).sum() < want_c.sum()
  assert float(drops.dip_share(jnp.asarray(x))) == pytest.approx(
      (want_d > 0).sum() / want_c.sum(), rel=1e-6)
  penalty = drops.dip_penalty
  assert float(penalty(jnp.asarray(x))) == pytest.approx(want_d.sum() / want_c.sum(), rel=1e-5)
  # The gradient moves each dip towards its neighbours and leaves them.
  g = np.asarray(jax.grad(penalty)(jnp.asarray(x)))
  np.testing.assert_allclose(g, np.where(want_d > 0, -1 / want_c.sum(), 0.0), rtol=1e-5)
  # Rings that vary smoothly all the way round have none; one pixel
  # pushed far behind its neighbours is one.
  smooth = np.broadcast_to(0.2 * np.cos(np.arange(12) * np.pi / 6), (1, 5, 12)).copy()
  assert float(penalty(jnp.asarray(smooth))) == 0.0
  smooth[0, 2, 6] -= 0.2
  assert float(penalty(jnp.asarray(smooth))) > 0.0
