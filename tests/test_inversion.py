"""GAN inversion: independence, restoration, edge cases, corruptions, CLI."""

import json
import os
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import dusty_jax
from dusty_jax import codec, corrupt, inversion, sampling, writers
from dusty_jax.codec import ALPHA
from conftest import FAST_COMPILE

HERE = os.path.dirname(__file__)


@pytest.fixture(scope='module')
def gen(smoke_run):
  params, _ = dusty_jax.load_checkpoint(smoke_run[1])
  return params


def _targets(params, n=3, seed=5):
  """Scans the generator can represent exactly: its own samples."""
  out = sampling.sample(params, jax.random.key(seed), n)
  return out['scan'], out['inv_depth']


def test_search_reduces_loss(gen):
  scans, _ = _targets(gen)
  short = inversion.invert(gen, scans, num_steps=2)
  long = inversion.invert(gen, scans, num_steps=60)
  assert (np.asarray(long['loss']) < np.asarray(short['loss'])).all()
  # Latents stay on the sphere of radius sqrt(d).
  np.testing.assert_allclose(np.linalg.norm(long['latent'], axis=-1),
                             np.sqrt(gen.latent_dim), rtol=1e-5)


def test_alone_and_in_batch_agree(gen):
  scans, _ = _targets(gen)
  keys = jax.random.split(jax.random.key(1), 3)
  batch = inversion.invert(gen, scans, key=keys, num_steps=20)
  alone = inversion.invert(gen, scans[1], key=keys[1:2], num_steps=20)
  np.testing.assert_allclose(alone['latent'], batch['latent'][1], rtol=1e-4, atol=1e-4)
  np.testing.assert_allclose(alone['loss'], batch['loss'][1], rtol=1e-3, atol=1e-6)
  assert alone['inv_depth'].shape == gen.sensor.shape


def test_restoring_90_percent_drop_beats_corrupted_input(gen):
  scans, _ = _targets(gen, n=2, seed=9)
  clean = np.asarray(scans)
  bad = corrupt.drop(jax.random.key(2), scans, 0.9)
  res = inversion.invert(gen, bad, num_steps=150)
  valid = clean > ALPHA
  # The corrupted input knows nothing at 90% of the clean valid pixels
  # (error vs alpha there); the reconstruction fills them in.
  err_input = np.abs(np.asarray(bad) - clean)[valid].mean()
  err_recon = np.abs(np.asarray(res['inv_depth']) - clean)[valid].mean()
  assert err_recon < err_input


def test_edge_cases(gen):
  h, w = gen.sensor.shape
  empty = jnp.full((h, w), ALPHA)
  with pytest.warns(UserWarning, match=r'scans \[0\] have no valid pixel'):
    out = inversion.invert(gen, empty, num_steps=5)
  assert all(np.isfinite(np.asarray(v)).all() for k, v in out.items()
             if k not in ('latent',) and np.asarray(v).dtype.kind == 'f')
  assert float(out['loss']) == 0
  nan_scan = jnp.full((1, h, w), 0.3).at[0, 0, :5].set(jnp.nan).at[0, 1, :5].set(jnp.inf)
  res = inversion.invert(gen, nan_scan, num_steps=5)
  assert np.isfinite(np.asarray(res['loss'])).all()
  mask = inversion.target_mask(nan_scan)
  assert not bool(mask[0, 0, :5].any()) and not bool(mask[0, 1, :5].any())
  with pytest.raises(ValueError, match='does not match'):
    inversion.invert(gen, jnp.zeros((4, 8)))


@pytest.mark.slow
def test_all_models_invert(tiny, tmp_path):
  from dusty_jax import trainer
  from train_helpers import tiny_config
  for name in ('baseline', 'dusty2'):
    setup = trainer.make_setup(tiny_config(model=name), tiny)
    state = trainer.init_state(setup, jax.random.key(0))
    params = trainer.generator_params(setup, state.g_params, tiny.nominal_angles())
    scans, _ = _targets(params, n=2)
    out = inversion.invert(params, scans, num_steps=3)
    assert out['inv_depth'].shape == (2,) + tiny.shape
    assert np.isfinite(np.asarray(out['loss'])).all()


def test_corruptions(tiny):
  d = np.random.default_rng(0).uniform(2, 80, (4,) + tiny.shape).astype(np.float32)
  x = codec.encode(d, tiny)
  dropped = corrupt.apply('drop:0.9', jax.random.key(0), x, tiny)
  kept = float(np.mean(np.asarray(dropped) > ALPHA))
  assert 0.06 < kept < 0.14
  beams = np.asarray(corrupt.apply('beams:4', None, x, tiny))
  assert (beams[:, 1::4] == ALPHA).all() and (beams[:, ::4] == np.asarray(x)[:, ::4]).all()
  noisy = corrupt.apply('noise:0.01', jax.random.key(1), x, tiny)
  nd, nv = codec.decode(noisy, tiny)
  resid = (np.asarray(nd) - d)[np.asarray(nv)]
  assert abs(resid.std() - 0.01 * (120 - 0.9)) < 0.1
  same = corrupt.apply('drop:0.5', jax.random.key(3), x, tiny)
  np.testing.assert_array_equal(same, corrupt.apply('drop:0.5', jax.random.key(3), x, tiny))
  for bad, msg in [('drop:1.5', 'must be in'), ('beams:2.5', 'whole number'),
                   ('blur:1', 'unknown corruption'), ('drop', 'NAME:VALUE')]:
    with pytest.raises(ValueError, match=msg):
      corrupt.parse(bad)


@pytest.mark.slow
def test_cli_on_files_and_split(smoke_run, tmp_path):
  from dusty_jax.data import kitti, scan_files, simulated_lidar
  config, workdir, _ = smoke_run
  params, _ = dusty_jax.load_checkpoint(workdir)
  inp = tmp_path / 'in'
  inp.mkdir()
  scan = simulated_lidar.render_scan(1, params.sensor)
  kitti.write_bin(str(inp / 'a.bin'), simulated_lidar.to_sensor_order(scan.depth, params.sensor))
  np.save(inp / 'b.npy', np.stack([scan.depth, scan.depth]))
  env = dict(os.environ)
  env['XLA_FLAGS'] = FAST_COMPILE  # one device
  out = tmp_path / 'out'
  r = subprocess.run([sys.executable, '-m', 'dusty_jax.tools.invert', '--workdir', workdir,
                      '--input', str(inp), '--corrupt', 'drop:0.5', '--out', str(out),
                      '--steps', '10'], env=env, capture_output=True, text=True,
                     timeout=600)
  assert r.returncode == 0, r.stderr[-3000:]
  for stem in ('a', 'b_00000', 'b_00001'):
    # (read_scans skips what INVERT_OUTPUTS names, should out be an input.)
    for suffix in (*scan_files.INVERT_OUTPUTS, '_depth.npy', '.ply', '.png'):
      assert (out / f'{stem}{suffix}').is_file(), f'{stem}{suffix}'
  assert writers.read_labels(str(out / 'b_00001.png')) == {
      'panels': ['clean scan', 'input scan', 'reconstruction x_tilde', 'measurability',
                 're-rendered scan'],
      'colour bars': [writers.COLOUR_BAR[k] for k in ('depth',) * 3 + ('probability', 'depth')]}
  m = json.load(open(out / 'metrics.json'))
  assert len(m['per_scan']) == 3 and 'AbsRel' in r.stdout and 'CD x1e4' in r.stdout
  r = subprocess.run([sys.executable, '-m', 'dusty_jax.tools.invert', '--workdir', workdir,
                      '--split', 'val', '--num', '2', '--steps', '5', '--out', str(out / 's')],
                     env=env, capture_output=True, text=True, timeout=600)
  assert r.returncode == 0, r.stderr[-3000:]
  # Simulated data: also against the ground truth only a simulator has.
  assert 'x_tilde vs complete depth' in r.stdout and 'ECE' in r.stdout
  assert 'nan' not in r.stdout.lower()  # the complete-depth table has no CD: n/a
  gt = json.load(open(out / 's' / 'metrics.json'))['ground_truth']
  assert 0 <= gt['ece'] <= 1 and np.isfinite(gt['complete_depth']['abs_rel'])
  # Drop placement beside the training split's per-ring table, which knows
  # nothing within a ring.
  assert gt['placement']['ece'] == pytest.approx(gt['ece'])
  assert gt['ring_table']['auc_near_within_ring'] in (0.5,) or np.isnan(
      gt['ring_table']['auc_near_within_ring'])
  assert 'keep rate per ring: AUC' in r.stdout
  assert (out / 's' / 'reliability.png').is_file()
  bad = subprocess.run([sys.executable, '-m', 'dusty_jax.tools.invert', '--workdir', workdir,
                        '--input', str(tmp_path / 'missing.bin')], env=env,
                       capture_output=True, text=True)
  assert bad.returncode != 0 and 'missing.bin: no such file' in bad.stderr


def test_render_drops_on_clean_scan(gen):
  _, complete = _targets(gen, n=2)
  out = inversion.render_drops(gen, complete, key=jax.random.key(4), num_samples=3,
                               num_steps=10)
  assert out['masks'].shape == (3, 2) + gen.sensor.shape
  m, s = np.asarray(out['masks']), np.asarray(out['scans'])
  # Kept pixels keep the clean scan's values exactly; the rest are drops.
  np.testing.assert_array_equal(s[m == 1], np.broadcast_to(np.asarray(complete), s.shape)[m == 1])
  assert (s[m == 0] == ALPHA).all()
  # Drop rate follows the fitted measurability.
  assert abs(m.mean() - float(np.asarray(out['measurability']).mean())) < 0.02
  single = inversion.render_drops(gen, complete[0], num_steps=5)
  assert single['scans'].shape == (1,) + gen.sensor.shape
  assert single['measurability'].shape == single['inversion']['inv_depth'].shape == (
      gen.sensor.shape)


def test_bad_inputs_get_clear_errors(gen, tiny):
  t = _targets(gen, n=1)[0]
  depth, _ = codec.decode(t, gen.sensor)
  with pytest.raises(ValueError, match=r'outside the normalised inverse depth.*codec\.encode'):
    inversion.invert(gen, depth, num_steps=2)  # metres by mistake
  with pytest.raises(ValueError, match='num_steps=-1'):
    inversion.invert(gen, t, num_steps=-1)
  with pytest.raises(ValueError, match='num_steps=2.5'):
    inversion.invert(gen, t, num_steps=2.5)
  with pytest.raises(ValueError, match='mask of shape'):
    inversion.invert(gen, t, mask=np.ones((3, 3), bool), num_steps=2)
  with pytest.raises(TypeError, match=r'jax\.random\.key\(3\)'):
    inversion.invert(gen, t, key=3, num_steps=2)
  with pytest.raises(ValueError, match='num=-1'):
    sampling.sample(gen, jax.random.key(0), -1)
  with pytest.raises(ValueError, match=rf'z of shape \(2, 5\): expected latents of shape '
                     rf'\(B, {gen.latent_dim}\)'):
    sampling.generate(gen, np.zeros((2, 5)), jax.random.key(1))
  with pytest.raises(TypeError, match=r'got the int 0; pass jax\.random\.key\(0\)'):
    sampling.generate(gen, np.zeros((2, gen.latent_dim)), 0)
  with pytest.raises(ValueError, match='num_samples=-1: must be a whole number >= 0'):
    inversion.render_drops(gen, t, num_samples=-1, num_steps=2)
  # A 2-D scan's shape is named as given, not with the batch axis invert adds.
  with pytest.raises(ValueError, match=r'scan of shape \(8, 16\) does not match'):
    inversion.render_drops(gen, t[0, :8, :16], num_steps=2)
  other = gen.replace(angles=jnp.zeros((2, 8, 8)))
  with pytest.raises(ValueError, match='angles of shape'):
    sampling.sample(other, jax.random.key(0), 2)


def test_legacy_prng_key_is_one_key(gen):
  """A legacy PRNGKey(0) means the typed key(0), not two per-scan keys."""
  t = _targets(gen, n=2)[0]
  a = inversion.invert(gen, t, key=jax.random.PRNGKey(0), num_steps=3)
  b = inversion.invert(gen, t, key=jax.random.key(0), num_steps=3)
  np.testing.assert_array_equal(np.asarray(a['latent']), np.asarray(b['latent']))
  s1 = sampling.sample(gen, jax.random.PRNGKey(4), 2)
  s2 = sampling.sample(gen, jax.random.key(4), 2)
  np.testing.assert_array_equal(np.asarray(s1['scan']), np.asarray(s2['scan']))


def test_cli_inputs_skip_a_bad_file(tiny, tmp_path):
  from dusty_jax.data import scan_files
  good = np.full(tiny.shape, 10.0, np.float32)
  np.save(tmp_path / 'a.npy', good)
  np.save(tmp_path / 'b.npy', np.zeros((3, 3), np.float32))  # wrong shape
  (tmp_path / 'c.bin').write_bytes(b'\0' * 20)  # not whole points
  logs = []
  items = scan_files.read_scans(str(tmp_path), tiny, log=logs.append)
  assert [n for n, _ in items] == ['a']
  assert any('2 of 3 input files skipped' in l for l in logs)
  assert any('b.npy' in l for l in logs) and any('c.bin' in l for l in logs)
  (tmp_path / 'a.npy').unlink()
  with pytest.raises(ValueError, match='none of 2 input files could be read'):
    scan_files.read_scans(str(tmp_path), tiny, log=logs.append)
  # A file given alone that is no scan file is named, with what it is.
  np.savez(tmp_path / 'g.npz', depth=good)
  np.save(tmp_path / 'o.npy', np.array([{'depth': 1}], dtype=object))
  (tmp_path / 'notes.txt').write_text('hello')
  for name, says in [('g.npz', 'not a scan file; give KITTI .bin files or .npy'),
                     ('o.npy', 'not a .npy array of numbers'),
                     ('notes.txt', 'not a scan file')]:
    logs = []
    with pytest.raises(ValueError, match='none of 1 input files'):
      scan_files.read_scans(str(tmp_path / name), tiny, log=logs.append)
    assert logs[0].startswith(f'skipped: {tmp_path / name}: {says}'), logs
  # A .npy that is a .npz archive inside.
  os.replace(tmp_path / 'g.npz', tmp_path / 'z.npy')
  logs = []
  with pytest.raises(ValueError, match='none of 1 input files'):
    scan_files.read_scans(str(tmp_path / 'z.npy'), tiny, log=logs.append)
  assert logs[0] == f'skipped: {tmp_path / "z.npy"}: a .npz archive, not a .npy array of metric depth'
  # invert's outputs as inputs (its --out given as --input): its re-rendered
  # scan is read; x_tilde and the measurability, whose values in (0, 1]
  # would pass for depth beyond the sensor's 0.9 m minimum, are not.
  out = tmp_path / 'out'
  out.mkdir()
  np.save(out / 'a_depth.npy', good)
  np.save(out / 'a_inv_depth.npy', np.full(tiny.shape, 0.95, np.float32))
  np.save(out / 'a_measurability.npy', np.full(tiny.shape, 0.95, np.float32))
  assert not scan_files.unusable_reason(np.load(out / 'a_measurability.npy'), tiny)
  logs = []
  assert [n for n, _ in scan_files.read_scans(str(out), tiny, log=logs.append)] == ['a_depth']
  assert logs[:2] == [
      f"skipped: {out / 'a_inv_depth.npy'}: invert's normalised inverse depth (x_tilde), "
      'not metric depth (a_depth.npy is its scan in metres)',
      f"skipped: {out / 'a_measurability.npy'}: invert's measurability, not metric depth "
      '(a_depth.npy is its scan in metres)'], logs
  # Normalised values in (0, 1] given as metres: most below the 0.9 m
  # minimum, a few above it. A metric scan with a tenth of its returns
  # beyond the maximum range is read.
  rng = np.random.default_rng(0)
  norm = rng.uniform(0.009, 1.0, tiny.shape).astype(np.float32)
  far = np.where(rng.uniform(size=tiny.shape) < 0.1, 150.0, 10.0).astype(np.float32)
  share = np.mean(norm > tiny.min_depth)
  assert 0 < share < 0.5
  assert scan_files.unusable_reason(far, tiny) is None
  assert scan_files.unusable_reason(norm, tiny) == (
      f"{share:.0%} of the returns lie inside the sensor's range ({tiny.min_depth}, "
      f'{tiny.max_depth}) m (values in [{norm.min():.3g}, {norm.max():.3g}]): normalised '
      'or already encoded scans given as metres? The input takes metric depth')


# The schedule and the projection before they were optax's, kept as the
# independent reference (StyleGAN2's projector, as the authors use it).
def _reference_lr(step, num_steps, lr=inversion.LR):
  t = step / num_steps
  g = np.minimum(1.0, (1.0 - t) / inversion.RAMP_DOWN)
  g = 0.5 - 0.5 * np.cos(g * np.pi)
  return lr * g * np.minimum(1.0, t / inversion.RAMP_UP)


def _reference_project(z):
  d = z.shape[-1]
  return z * np.sqrt(d) / np.maximum(np.linalg.norm(z, axis=-1, keepdims=True), 1e-12)


@pytest.mark.parametrize('num_steps', [1, 2, 7, 20, 30, 101, 1000])
def test_lr_schedule_matches_stylegan2_projector(num_steps):
  steps = np.arange(num_steps + 1)
  want = _reference_lr(steps.astype(np.float64), num_steps)
  # As optax.adam calls it: an int32 count, under jit.
  schedule = jax.jit(inversion.lr_schedule(num_steps))
  got = np.array([schedule(jnp.int32(s)) for s in steps])
  np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7 * inversion.LR)
  assert got[0] == 0 and abs(got[-1]) <= 1e-7 * inversion.LR
  # A traced lr (invert() jits it) scales the whole schedule.
  scaled = jax.jit(lambda s, lr: inversion.lr_schedule(num_steps, lr)(s))
  np.testing.assert_allclose(scaled(jnp.int32(num_steps // 2), 0.5),
                             _reference_lr(num_steps // 2, num_steps, 0.5), rtol=1e-6)


def test_project_matches_reference_and_lands_on_sphere():
  rng = np.random.default_rng(0)
  for d in (1, 3, 512):
    z = rng.normal(scale=rng.uniform(0.01, 100), size=(6, d)).astype(np.float32)
    got = np.asarray(inversion.project(jnp.asarray(z)))
    np.testing.assert_allclose(got, _reference_project(z.astype(np.float64)),
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(got, axis=-1), np.sqrt(d), rtol=1e-6)
    # One vector alone is projected as inside a batch.
    np.testing.assert_allclose(np.asarray(inversion.project(jnp.asarray(z[2]))), got[2],
                               rtol=1e-6)
  # Points already on the sphere stay put.
  np.testing.assert_allclose(np.asarray(inversion.project(jnp.asarray(got))), got,
                             rtol=1e-6, atol=1e-6)


def test_project_zero_and_tiny_vectors():
  d = 8
  # Zero: no direction to keep; a finite point on the sphere (all ones).
  zero = np.asarray(inversion.project(jnp.zeros(d)))
  np.testing.assert_array_equal(zero, np.ones(d, np.float32))
  # Norms whose square underflows float32 (1e-30^2, 1e-37^2, near the
  # smallest normal number) or overflows it (1e30^2) keep their direction and
  # land on the sphere. (XLA flushes subnormals to zero: those are zero here.)
  direction = np.array([3, -4, 0, 1, 0, 0, 2, -1], np.float64)
  for scale in (1e-30, 1e-37, 1e30):
    z = jnp.asarray(direction * scale / np.abs(direction).max(), jnp.float32)
    got = np.asarray(inversion.project(z))
    assert np.isfinite(got).all()
    np.testing.assert_allclose(np.linalg.norm(got), np.sqrt(d), rtol=1e-6)
    # The exact projection, in float64 (the old formula's 1e-12 floor on the
    # norm left such z off the sphere, and float32 squares underflow).
    z64 = np.asarray(z, np.float64)
    np.testing.assert_allclose(got, z64 * np.sqrt(d) / np.linalg.norm(z64),
                               rtol=1e-6, atol=1e-6)
  # Gradients through the projection (the search never takes them, a user may)
  # stay finite at zero too.
  grad = jax.grad(lambda z: inversion.project(z).sum())(jnp.zeros(d))
  assert np.isfinite(np.asarray(grad)).all()


def test_given_start_equals_random_start_and_is_checked(gen):
  scans, _ = _targets(gen)
  key = jax.random.key(4)
  keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(3))
  z0 = inversion.random_start(gen, scans, None, keys)
  a = inversion.invert(gen, scans, key=key, num_steps=10)
  # Given latents off the sphere are projected: x3 is the same start.
  b = inversion.invert(gen, scans, key=key, num_steps=10, init=3.0 * z0)
  np.testing.assert_allclose(b['latent'], a['latent'], rtol=1e-5, atol=1e-5)
  one = inversion.invert(gen, scans[0], key=keys[0:1], num_steps=10, init=z0[0])
  np.testing.assert_allclose(one['latent'], a['latent'][0], rtol=1e-5, atol=1e-5)
  with pytest.raises(ValueError, match=r'init latents of shape \(2, \d+\): expected \(3, '):
    inversion.invert(gen, scans, num_steps=1, init=z0[:2])
  with pytest.raises(ValueError, match=r"init='encoderr': known starts are \['encoder', 'random'\]"):
    inversion.invert(gen, scans, num_steps=1, init='encoderr')


def test_objective_and_a_replaced_loss(gen):
  x = jnp.array([[0.5, -0.5], [0.0, 1.0]])
  t = jnp.array([[0.0, 0.0], [0.0, 0.0]])
  m = jnp.array([[True, True], [False, False]])
  assert float(inversion.objective(x, t, m)) == pytest.approx(0.5)
  assert float(inversion.objective(x, t, jnp.zeros_like(m))) == 0.0
  # A loss with no gradient leaves the start where it was.
  scans, _ = _targets(gen, n=2)
  z0 = jax.random.normal(jax.random.key(8), (2, gen.latent_dim))
  flat = lambda x_tilde, target, mask: 0.0 * jnp.sum(x_tilde)
  out = inversion.invert(gen, scans, num_steps=5, init=z0, loss=flat)
  np.testing.assert_allclose(out['latent'], inversion.project(z0), rtol=1e-5, atol=1e-5)
  assert (np.asarray(out['loss']) == 0).all()


@pytest.mark.parametrize('lr', [float('nan'), float('inf'), 0.0, -0.1])
def test_a_learning_rate_that_cannot_work_is_refused(gen, lr):
  """Without the check every latent ended at the all-ones point, silently."""
  t = _targets(gen, n=1)[0]
  with pytest.raises(ValueError, match=r'lr=.*must be a finite number > 0'):
    inversion.invert(gen, t, num_steps=2, lr=lr)


def test_empty_in_empty_out(gen):
  """sample(num=0) and invert of 0 scans agree: numpy's rule."""
  h, w = gen.sensor.shape
  out = sampling.sample(gen, jax.random.key(0), 0)
  assert out['scan'].shape == (0, h, w) and out['points'].shape == (0, h, w, 3)
  assert sampling.sample_scans(gen, jax.random.key(0), 0).shape == (0, h, w)
  rec = inversion.invert(gen, np.zeros((0, h, w), np.float32), num_steps=2)
  assert rec['inv_depth'].shape == (0, h, w) and rec['latent'].shape == (0, gen.latent_dim)
  assert set(rec) >= set(out)
  with pytest.raises(ValueError, match='num=-1'):
    sampling.sample(gen, jax.random.key(0), -1)
  with pytest.raises(ValueError, match=rf'z of shape \(2, 5\): expected latents of shape '
                     rf'\(B, {gen.latent_dim}\)'):
    sampling.generate(gen, np.zeros((2, 5)), jax.random.key(1))


def _real_and_simulated_depths(sensor):
  """Metric depth of KITTI-layout scans (unfolded from sensor-order points)
  and of simulated ones."""
  from conftest import random_depth, sensor_order_points
  from dusty_jax.data import simulated_lidar, unfolding
  real = [unfolding.unfold(sensor_order_points(random_depth(sensor, seed=s), sensor, seed=s),
                           sensor, firing_order=True).depth
          for s in range(3)]
  sim = [simulated_lidar.render_scan(s, sensor).depth for s in range(3)]
  return np.stack(real), np.stack(sim)


def test_scans_not_encoded_are_warned_about_and_real_ones_never(gen):
  """depth / max_depth lies inside [-1, 1] but has no value below
  0 and no drop; genuine encoded scans always have both."""
  import warnings
  real, sim = _real_and_simulated_depths(gen.sensor)
  for depth in (real, sim):
    with warnings.catch_warnings():
      warnings.simplefilter('error')
      inversion.invert(gen, codec.encode(depth, gen.sensor), num_steps=2)
      inversion.invert(gen, codec.encode(depth[0], gen.sensor), num_steps=2)
  with pytest.warns(UserWarning, match=r'scans \[0, 1, 2\] have no value below 0 and '
                    r'no drop.*depth / max_depth.*codec\.encode'):
    inversion.invert(gen, sim / gen.sensor.max_depth, num_steps=2)
  with pytest.warns(UserWarning, match=r'the scan has no value below 0'):
    inversion.invert(gen, real[0] / gen.sensor.max_depth, num_steps=2)


def test_invert_cli_skips_encoded_scans_given_as_metres(smoke_run, tmp_path, capsys):
  """The file and the reason, skipped as prepare skips; no NaN
  table; a non-zero exit when no scan could be fitted."""
  from dusty_jax.tools import invert as invert_tool
  _, workdir, _ = smoke_run
  params, _ = dusty_jax.load_checkpoint(workdir)
  _, sim = _real_and_simulated_depths(params.sensor)
  inp = tmp_path / 'in'
  inp.mkdir()
  np.save(inp / 'encoded.npy', np.asarray(codec.encode(sim[0], params.sensor)))
  np.save(inp / 'metres.npy', sim[1])
  invert_tool.main(['--workdir', workdir, '--input', str(inp), '--out',
                    str(tmp_path / 'out'), '--steps', '3'])
  out = capsys.readouterr().out
  assert re.search(r"skipped: \S*encoded\.npy: every depth is below the sensor's "
                   r'minimum range of [\d.]+ m', out), out
  assert 'nan' not in out.lower() and 'protocol reference: 1 scans' in out
  per_scan = json.load(open(tmp_path / 'out' / 'metrics.json'))['per_scan']
  assert [r['name'] for r in per_scan] == ['metres']
  (inp / 'metres.npy').unlink()
  with pytest.raises(SystemExit, match='none of 1 input files could be read or holds '
                     'a scan to fit') as e:
    invert_tool.main(['--workdir', workdir, '--input', str(inp), '--out',
                      str(tmp_path / 'out2'), '--steps', '3'])
  assert e.value.code == 1
  assert 'encoded.npy' in capsys.readouterr().out


def test_restoration_draws_per_scan_whatever_the_batch(gen):
  """evaluation.restoration (Table III, what the invert tool prints): scan i
  is corrupted with fold_in(k_corrupt, i) and searched from
  fold_in(k_search, i), so two batch sizes give one record, equal to
  corrupt.apply + invert called on that scan alone."""
  from dusty_jax import evaluation
  from dusty_jax.metrics import reconstruction
  _, complete = _targets(gen, n=2, seed=11)
  depth = np.asarray(codec.decode(complete, gen.sensor)[0])
  kw = dict(corruption='drop:0.5', num_steps=8, seed=3, protocol_name='reference')
  one = evaluation.restoration(gen, depth, batch=1, **kw)
  two = evaluation.restoration(gen, depth, batch=2, **kw)
  for a, b in zip(one['per_scan'], two['per_scan']):
    assert a['name'] == b['name']
    for k in ('abs_rel', 'cd', 'loss'):
      assert a[k] == pytest.approx(b[k], rel=1e-3, abs=1e-6), k
  k_corrupt, k_search = jax.random.split(jax.random.key(3))
  i = 1
  clean = codec.encode(depth[i], gen.sensor)
  target = corrupt.apply('drop:0.5', jax.random.fold_in(k_corrupt, i), clean, gen.sensor)
  res = jax.device_get(inversion.invert(gen, target[None], num_steps=8,
                                        key=jax.random.fold_in(k_search, i)[None]))
  errs = reconstruction.errors(depth[i:i + 1], res, np.asarray(gen.angles), gen.sensor)
  assert one['per_scan'][i]['abs_rel'] == pytest.approx(float(errs['abs_rel'][0]), rel=1e-4)
  assert one['per_scan'][i]['loss'] == pytest.approx(float(res['loss'][0]), rel=1e-3)
  assert one['num'] == 2 and one['corrupt'] == 'drop:0.5' and one['seeds']['batch'] == 1
  cols = [k for k, _, _ in reconstruction.COLUMNS]
  for k in cols:
    assert one['mean'][k] == pytest.approx(np.mean([r[k] for r in one['per_scan']]),
                                           rel=1e-6)
  json.dumps(one)


def test_a_scan_with_nothing_to_compare_leaves_no_nan_in_the_table(gen):
  """A scan with no valid return has no Chamfer distance: the mean is over
  the scans that have one, an empty column is None (null in JSON), and the
  table prints n/a, never nan."""
  from dusty_jax import evaluation
  from dusty_jax.metrics import records, reconstruction
  _, complete = _targets(gen, n=2, seed=12)
  depth = np.array(codec.decode(complete, gen.sensor)[0])
  depth[1] = 0.0
  with pytest.warns(UserWarning, match='no valid pixel'):
    rec = evaluation.restoration(gen, depth, num_steps=2, names=['a', 'b'])
  cd = [r['cd'] for r in rec['per_scan']]
  assert np.isfinite(cd[0]) and np.isnan(cd[1])
  assert rec['mean']['cd'] == pytest.approx(cd[0])
  assert records.finite_mean([np.nan, np.inf]) is None
  table = records.format_table({'x': {**rec['mean'], 'cd': None},
                                 'y': {'abs_rel': [np.nan, 0.5]}}, reconstruction.COLUMNS)
  assert 'nan' not in table.lower() and table.count('n/a') == 1 + 7
  assert '0.500' in table


def _old_static_search(params, scan, key, num_steps, lr=inversion.LR):
  """The search as invert() ran it with num_steps static (before it was
  traced): optax's schedules joined by optax.join_schedules, a plain Python
  loop of the step, from the random start. Returns the latent (d,)."""
  n = max(num_steps, 1)
  up, down = inversion.RAMP_UP * n, inversion.RAMP_DOWN * n
  schedule = optax.join_schedules(
      [optax.linear_schedule(0.0, lr, up), optax.constant_schedule(lr),
       optax.cosine_decay_schedule(lr, down)], boundaries=[up, n - down])
  tx = optax.adam(schedule)
  mask = inversion.target_mask(scan)
  target = jnp.where(mask, scan, 0.0)
  apply = params.module().apply
  kz, kn = jax.random.split(key)
  z = inversion.project(jax.random.normal(kz, (params.latent_dim,)))
  opt = tx.init(z)

  @jax.jit
  def step(i, z, opt):
    t = i / num_steps
    strength = inversion.NOISE_SCALE * jnp.maximum(0.0, 1.0 - t / inversion.NOISE_RAMP) ** 2
    noise = strength * jax.random.normal(jax.random.fold_in(kn, i), z.shape)
    grad = jax.grad(lambda z: inversion.scan_loss(params, apply, z + noise, target, mask))(z)
    updates, opt = tx.update(grad, opt, z)
    return inversion.project(optax.apply_updates(z, updates)), opt

  for i in range(num_steps):
    z, opt = step(i, z, opt)
  return np.asarray(z)


@pytest.mark.parametrize('num_steps', [7, 25])
def test_traced_step_count_follows_the_old_static_search(num_steps):
  """num_steps is a traced loop bound now; each scan's latent is the one the
  old static loop reached, and the schedule is optax's at every step."""
  from dusty_jax import trainer
  from dusty_jax.sensor import tiny_sensor
  from train_helpers import tiny_config
  sensor = tiny_sensor(16, 64)
  setup = trainer.make_setup(tiny_config(), sensor)
  state = trainer.init_state(setup, jax.random.key(0))
  params = trainer.generator_params(setup, state.g_params, sensor.nominal_angles())
  scans, _ = _targets(params, n=2)
  key = jax.random.key(3)
  got = np.asarray(inversion.invert(params, scans, key=key, num_steps=num_steps)['latent'])
  for i in range(2):
    want = _old_static_search(params, scans[i], jax.random.fold_in(key, i), num_steps)
    np.testing.assert_allclose(got[i], want, rtol=1e-4, atol=1e-4)
  n = num_steps
  old = optax.join_schedules(
      [optax.linear_schedule(0.0, 0.3, inversion.RAMP_UP * n), optax.constant_schedule(0.3),
       optax.cosine_decay_schedule(0.3, inversion.RAMP_DOWN * n)],
      boundaries=[inversion.RAMP_UP * n, n - inversion.RAMP_DOWN * n])
  traced = jax.jit(lambda s, n: inversion.lr_schedule(n, 0.3)(s))
  for s in range(n + 1):
    np.testing.assert_allclose(traced(jnp.int32(s), jnp.int32(n)), old(jnp.int32(s)),
                               rtol=1e-6, atol=1e-9)


def test_a_new_step_count_or_start_compiles_no_new_search(gen):
  """The search program is compiled once per shape, whatever num_steps and
  init are: a new count or start must not cost a compilation (50-100 s of a
  CPU's time when each compiled again)."""
  scans, _ = _targets(gen, n=2)
  inversion.invert(gen, scans, num_steps=3)
  size = inversion._search._cache_size()
  z0 = jax.random.normal(jax.random.key(1), (2, gen.latent_dim))
  for steps, init in ((4, 'random'), (11, 'random'), (0, 'random'), (5, z0)):
    inversion.invert(gen, scans, num_steps=steps, init=init)
  assert inversion._search._cache_size() == size
