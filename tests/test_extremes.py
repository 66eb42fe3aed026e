"""Numerical stability at the extremes, swept over the public entry points.

Each test is a row: an entry point given an extreme (zeros, constants,
+-1e38, +-inf, NaN, empty, one element, all dropped, the sensor's range and
just past it, int32's limit for counts, half precision) and its contract:
a finite answer that a property or an independent computation checks, or
one errors.InputError (or configs.ConfigError) that names the value. Tiny
shapes: a 16x64 DUSty-I of random weights, 16 latent dimensions.
Training at the extremes of its settings is in test_train_extremes.py.
"""

import math

import jax
import jax.numpy as jnp
import ml_dtypes
import numpy as np
import pytest
import scipy.ndimage

from dusty_jax import (codec, configs, encoder, errors, generator, gumbel, inversion, levels,
                       losses, sampling, trainer)
from dusty_jax.codec import ALPHA
from dusty_jax.metrics import calibration, chamfer, compare, depth, point_sets, swd
from dusty_jax.models import ModelSettings
from dusty_jax.sensor import tiny_sensor

F32_MAX = float(np.finfo(np.float32).max)
HALF = (np.float16, ml_dtypes.bfloat16)
NON_FINITE = [math.nan, math.inf, -math.inf]


@pytest.fixture(scope='module')
def gen():
  """A tiny DUSty-I of random weights, with a tiny encoder."""
  sensor = tiny_sensor(16, 64)
  settings = ModelSettings(model='dusty1', latent_dim=16, ch_base=8, ch_max=16)
  variables = settings.generator(sensor).init(jax.random.key(0), jnp.zeros((1, 16)))
  params = generator.GeneratorParams(
      variables=variables, angles=jnp.asarray(sensor.nominal_angles(), jnp.float32),
      sensor=sensor, settings=settings)
  enc_settings = encoder.EncoderSettings(ch_base=4, ch_max=8, hidden=16)
  enc = jax.jit(encoder.Encoder(sensor, 16, enc_settings, 'xla').init)(
      jax.random.key(1), jnp.zeros((1,) + sensor.shape))
  return params.replace(encoder=enc, encoder_settings=enc_settings)


@pytest.fixture(scope='module')
def scans(gen):
  """Two of the generator's own scans (drops at ALPHA, returns above it)."""
  return np.asarray(sampling.sample(gen, jax.random.key(3), 2)['scan'])


def _on_sphere(z, d):
  z = np.asarray(z)
  assert np.isfinite(z).all()
  np.testing.assert_allclose(np.linalg.norm(z, axis=-1), np.sqrt(d), rtol=1e-5)


# ----------------------------------------------------------------------------
# invert
# ----------------------------------------------------------------------------


@pytest.mark.parametrize('bad', NON_FINITE)
def test_invert_refuses_a_non_finite_initial_latent(gen, scans, bad):
  """Issue row: NaN in init was silently replaced by the all-ones point;
  inf gave NaN. Now: InputError naming init and the value."""
  z = np.ones((2, 16), np.float32)
  z[1, 3] = bad
  with pytest.raises(errors.InputError, match=rf'init latents: 1 of 32 .*{bad!r}.* \(1, 3\)'):
    inversion.invert(gen, scans, init=z, num_steps=3)


@pytest.mark.parametrize('scale', [1e-30, 1.0, 1e30, 9e37, F32_MAX])
def test_invert_starts_on_the_sphere_from_init_of_any_finite_scale(gen, scans, scale):
  """Issue row: max|z| >= 8.6e37 projected to NaN (1 / max|z| flushed to 0)
  and the search stayed at the all-ones point. Now any finite scale gives
  the direction of z on the sphere, and the search moves from there."""
  u = np.random.default_rng(0).uniform(-1, 1, (2, 16)).astype(np.float32)
  u[:, 0] = 1.0  # max |u| = 1, so u * scale stays finite
  want = u / np.linalg.norm(u, axis=-1, keepdims=True) * 4.0  # sqrt(16)
  start = inversion.invert(gen, scans, init=u * np.float32(scale), num_steps=0)
  np.testing.assert_allclose(start['latent'], want, rtol=1e-5, atol=1e-6)
  moved = inversion.invert(gen, scans, init=u * np.float32(scale), num_steps=3)
  _on_sphere(moved['latent'], 16)
  assert np.isfinite(np.asarray(moved['loss'])).all()
  assert not np.allclose(moved['latent'], want, atol=1e-3)


@pytest.mark.parametrize('steps', [2 ** 31, -1, 2.0, True])
def test_invert_refuses_a_step_count_outside_int32(gen, scans, steps):
  """Issue row: num_steps=2**31 raised OverflowError from numpy."""
  with pytest.raises(errors.InputError, match=rf'num_steps={steps!r}: must be a whole '
                     r'number >= 0 and <= 2\*\*31 - 1'):
    inversion.invert(gen, scans, num_steps=steps)


def test_invert_of_non_finite_and_all_dropped_pixels(gen, scans):
  """inf and NaN pixels count as drops (the documented contract): the same
  result as ALPHA there; a scan of drops only stays at its start, warned."""
  bad = scans.copy()
  bad[0, :2] = np.inf
  bad[0, 2:4, :10] = -np.inf
  bad[1, 5, 5] = np.nan
  clean = np.where(np.isfinite(bad), bad, ALPHA)
  a = inversion.invert(gen, bad, num_steps=2)
  b = inversion.invert(gen, clean, num_steps=2)
  np.testing.assert_array_equal(a['latent'], b['latent'])
  dropped = np.full_like(scans, ALPHA)
  with pytest.warns(UserWarning, match=r'scans \[0, 1\] have no valid pixel'):
    out = inversion.invert(gen, dropped, num_steps=3)
  with pytest.warns(UserWarning, match='no valid pixel'):
    start = inversion.invert(gen, dropped, num_steps=0)
  np.testing.assert_allclose(out['latent'], start['latent'], rtol=1e-6)
  assert np.isfinite(np.asarray(out['loss'])).all() and (np.asarray(out['loss']) == 0).all()


@pytest.mark.parametrize('dtype', HALF)
def test_invert_refuses_a_half_precision_scan(gen, scans, dtype):
  with pytest.raises(errors.InputError, match=f'scan in {np.dtype(dtype).name}'):
    inversion.invert(gen, scans.astype(dtype), num_steps=0)


@pytest.mark.parametrize('lr', [0.0, math.inf, math.nan, -1.0])
def test_invert_refuses_a_learning_rate_that_cannot_search(gen, scans, lr):
  with pytest.raises(ValueError, match=f'lr={lr!r}'):
    inversion.invert(gen, scans, num_steps=2, lr=lr)


def test_invert_of_an_empty_batch_is_empty(gen):
  out = inversion.invert(gen, np.zeros((0, 16, 64), np.float32), num_steps=2)
  assert out['latent'].shape == (0, 16) and out['scan'].shape == (0, 16, 64)


# ----------------------------------------------------------------------------
# generate, sample
# ----------------------------------------------------------------------------


@pytest.mark.parametrize('bad', NON_FINITE + [1e38, -1e38, 1.5 * sampling.MAX_LATENT])
def test_generate_refuses_latents_it_cannot_render(gen, bad):
  """Issue row: latents of 1e38, inf or NaN made the whole scan NaN."""
  z = np.zeros((2, 16), np.float32)
  z[1, 5] = bad
  with pytest.raises(errors.InputError, match=r'^z: '):
    sampling.generate(gen, z, jax.random.key(0))


@pytest.mark.parametrize('value', [0.0, -sampling.MAX_LATENT, sampling.MAX_LATENT])
def test_generate_at_the_latent_limits_is_finite(gen, value):
  """Zero latents and the largest accepted component give a finite scan:
  drops at exactly ALPHA, returns in (ALPHA, 1], depths in the sensor's
  range where valid."""
  z = np.full((2, 16), value, np.float32)
  z[1, ::2] = -value
  out = jax.device_get(sampling.generate(gen, z, jax.random.key(0)))
  for k in ('inv_depth', 'measurability', 'scan', 'depth', 'points'):
    assert np.isfinite(out[k]).all(), k
  scan, valid = out['scan'], out['valid']
  assert ((scan == ALPHA) | (scan > ALPHA)).all() and (scan <= 1).all()
  d = out['depth'][valid]
  assert ((d > gen.sensor.min_depth * 0.999) & (d < gen.sensor.max_depth * 1.001)).all()


@pytest.mark.parametrize('dtype', HALF)
def test_half_precision_latents_and_weights_compute_in_float32(gen, dtype):
  """Decision: half-precision latents and generator weights are cast to
  float32 where they enter: the answer is the float32 one of their rounded
  values, in float32."""
  z = np.random.default_rng(1).normal(size=(2, 16)).astype(dtype)
  key = jax.random.key(4)
  want = sampling.generate(gen, z.astype(np.float32), key)
  got = sampling.generate(gen, z, key)
  assert got['scan'].dtype == jnp.float32
  np.testing.assert_array_equal(got['inv_depth'], want['inv_depth'])
  half = gen.replace(variables=jax.tree.map(lambda v: v.astype(dtype), gen.variables))
  rounded = gen.replace(variables=jax.tree.map(
      lambda v: v.astype(dtype).astype(np.float32), gen.variables))
  got = sampling.generate(half, z.astype(np.float32), key)
  want = sampling.generate(rounded, z.astype(np.float32), key)
  assert got['inv_depth'].dtype == jnp.float32
  np.testing.assert_array_equal(got['inv_depth'], want['inv_depth'])
  assert np.isfinite(np.asarray(got['scan'])).all()
  np.testing.assert_array_equal(sampling.sample(half, key, 1)['scan'],
                                sampling.sample(rounded, key, 1)['scan'])


@pytest.mark.parametrize('num', [2 ** 31, -1, 1.0])
def test_sample_refuses_a_count_outside_int32(gen, num):
  with pytest.raises(errors.InputError, match=rf'num={num!r}: must be a whole number'):
    sampling.sample(gen, jax.random.key(0), num)


@pytest.mark.parametrize('num', [0, 1])
def test_sample_of_none_and_of_one(gen, num):
  out = sampling.sample(gen, jax.random.key(0), num)
  assert out['scan'].shape == (num, 16, 64)
  assert np.isfinite(np.asarray(out['scan'])).all()


# ----------------------------------------------------------------------------
# encoder.encode, project
# ----------------------------------------------------------------------------


@pytest.mark.parametrize('fill', ['all dropped', 'all nearest', 'non-finite'])
def test_encode_of_extreme_scans_is_on_the_sphere(gen, scans, fill):
  """Scans of drops only, of returns at the near end only, or with NaN and
  inf pixels (drops, as in invert) give latents on the sphere."""
  x = scans.copy()
  if fill == 'all dropped':
    x[:] = ALPHA
  elif fill == 'all nearest':
    x[:] = 1.0
  else:
    x[0, :8], x[1, :, :5] = np.nan, np.inf
  z = encoder.encode(gen, x)
  _on_sphere(z, 16)
  if fill == 'non-finite':
    np.testing.assert_array_equal(z, encoder.encode(gen, np.where(np.isfinite(x), x, ALPHA)))


@pytest.mark.parametrize('dtype', HALF)
def test_encode_refuses_half_scans_and_widens_half_weights(gen, scans, dtype):
  with pytest.raises(errors.InputError, match=f'scans in {np.dtype(dtype).name}'):
    encoder.encode(gen, scans.astype(dtype))
  half = gen.replace(encoder=jax.tree.map(lambda v: v.astype(dtype), gen.encoder))
  rounded = gen.replace(encoder=jax.tree.map(lambda v: v.astype(dtype).astype(np.float32),
                                             gen.encoder))
  got = encoder.encode(half, scans)
  assert got.dtype == jnp.float32
  np.testing.assert_array_equal(got, encoder.encode(rounded, scans))


@pytest.mark.parametrize('scale', [1e-30, 1e-10, 1.0, 1e10, 1e37, 9e37, F32_MAX])
def test_project_is_stable_for_any_finite_scale(scale):
  """project(z * s) = project(z): scaled before it is normalised, so
  neither the norm's square nor the reciprocal of max|z| leaves float32."""
  z = np.linspace(-1, 1, 16, dtype=np.float32)
  got = np.asarray(encoder.project(jnp.asarray(z * np.float32(scale))))
  np.testing.assert_allclose(got, z / np.linalg.norm(z) * 4.0, rtol=1e-5, atol=1e-6)
  # Zero has no direction: the all-ones point, on the sphere.
  np.testing.assert_array_equal(encoder.project(jnp.zeros(16)), np.ones(16))


# ----------------------------------------------------------------------------
# gumbel, losses
# ----------------------------------------------------------------------------


@pytest.mark.parametrize('tau', [1e-45, 0.0, -1.0, math.inf, math.nan])
def test_gumbel_refuses_a_temperature_that_flushes_or_overflows(tau):
  """Issue row: tau = 1e-45 gave a NaN mask and NaN gradients; inf dropped
  every pixel with zero gradient."""
  with pytest.raises(errors.InputError, match=f'tau={tau!r}'):
    gumbel.straight_through(jnp.zeros(3), jnp.zeros(3), tau)
  with pytest.raises(ValueError, match=f'tau={tau!r}'):
    ModelSettings(tau=tau)


@pytest.mark.parametrize('bad', NON_FINITE)
def test_gumbel_refuses_a_non_finite_logit(bad):
  """Issue row: a NaN logit gave a NaN mask, neither 0 nor 1."""
  logits = jnp.array([0.5, bad, -0.5])
  with pytest.raises(errors.InputError, match=r'logits: 1 of 3'):
    gumbel.pixel_mask(jax.random.key(0), logits)
  with pytest.raises(errors.InputError, match=r'logits: 1 of 3'):
    gumbel.image_mask(jax.random.key(0), logits[:, None], train=False)


@pytest.mark.parametrize('tau', [gumbel.TINY, *gumbel.TAU_RANGE, 1e30])
def test_gumbel_at_the_temperature_limits(tau):
  """At the accepted ends (and the training range's) the mask is exactly 0
  or 1 and the gradient is the soft mask's, computed here apart."""
  noise = gumbel.logistic_from_uniform(jnp.array([0.0, 1.0, 0.5, 0.5, 0.3]))
  near = 0.3 * max(tau, 1e-3)  # where the soft mask is not saturated (tau >= 1e-3)
  logits = jnp.array([1e4, -1e4, near, -near, 1e-3], jnp.float32)
  mask = np.asarray(gumbel.straight_through(logits, noise, tau))
  assert set(mask.tolist()) <= {0.0, 1.0}
  np.testing.assert_array_equal(mask, np.asarray((logits + noise) / tau > 0, np.float32))
  grad = np.asarray(jax.grad(lambda l: gumbel.straight_through(l, noise, tau).sum())(logits))
  zz = np.asarray((logits + noise) / np.float32(tau), np.float64)
  with np.errstate(over='ignore'):  # exp(-zz) = inf: s = 0, as float32's
    s = 1 / (1 + np.exp(-zz))
  np.testing.assert_allclose(grad, s * (1 - s) / tau, rtol=1e-4, atol=1e-30)
  assert np.isfinite(grad).all()


@pytest.mark.parametrize('big', [1e4, 1e38, F32_MAX])
def test_losses_at_saturated_logits(big):
  """The non-saturating losses of logits up to float32's largest are finite
  and equal log(1 + e^-x) computed in float64."""
  sp = lambda x: np.logaddexp(0.0, np.asarray(x, np.float64))
  real = np.array([big, -big, 0.0], np.float32)
  fake = np.array([-big, big, 0.0], np.float32)
  d = float(losses.d_loss(jnp.asarray(real), jnp.asarray(fake)))
  g = float(losses.g_loss(jnp.asarray(fake)))
  np.testing.assert_allclose(d, sp(-real).mean() + sp(fake).mean(), rtol=1e-6)
  np.testing.assert_allclose(g, sp(-fake).mean(), rtol=1e-6)


@pytest.mark.parametrize('bad', NON_FINITE)
def test_losses_refuse_non_finite_logits(bad):
  with pytest.raises(errors.InputError, match='logits'):
    losses.g_loss(jnp.array([0.0, bad]))
  with pytest.raises(errors.InputError, match='fake logits'):
    losses.d_loss(jnp.zeros(2), jnp.array([bad, 0.0]))


@pytest.mark.parametrize('x', [0.0, ALPHA, 1.0])
def test_r1_at_the_code_ends(x):
  """R1 of a linear discriminator is |w|^2 wherever x is; of a constant one 0."""
  w = jnp.linspace(-1, 1, 16 * 64).reshape(16, 64)
  xs = jnp.full((2, 16, 64), x)
  r1 = float(losses.r1_penalty(lambda v: jnp.sum(v * w, (1, 2)), xs))
  np.testing.assert_allclose(r1, float(np.sum(np.square(np.asarray(w, np.float64)))), rtol=1e-5)
  assert float(losses.r1_penalty(lambda v: jnp.zeros(len(v)), xs)) == 0.0


# ----------------------------------------------------------------------------
# codec
# ----------------------------------------------------------------------------


def test_codec_at_and_just_past_the_sensors_range(kitti):
  """Valid strictly inside (min, max): those encode above ALPHA and decode
  back; at and past each end, 0, negative, NaN, +-inf and 1e38: ALPHA."""
  lo, hi = np.float32(kitti.min_depth), np.float32(kitti.max_depth)
  inside = np.array([np.nextafter(lo, hi), lo * 1.001, hi * 0.999, np.nextafter(hi, lo)],
                    np.float32)
  x = np.asarray(codec.encode(inside, kitti))
  assert (x > ALPHA).all() and (x <= 1).all()
  d, valid = codec.decode(x, kitti)
  assert np.asarray(valid).all()
  np.testing.assert_allclose(d, inside, rtol=1e-4)
  outside = np.array([lo, hi, np.nextafter(lo, 0), np.nextafter(hi, np.inf), 0, -1, np.nan,
                      np.inf, -np.inf, 1e38, -1e38], np.float32)
  assert (np.asarray(codec.encode(outside, kitti)) == ALPHA).all()
  d, valid = codec.decode(np.array([ALPHA, np.nan, np.inf, -np.inf, -1e38]), kitti)
  assert not np.asarray(valid).any() and (np.asarray(d) == 0).all()


@pytest.mark.parametrize('dtype', HALF)
def test_decode_refuses_half_precision_codes(kitti, dtype):
  """Issue row: a scan rounded through bfloat16 decoded 110 and 119 m as
  drops and 100 m as 95.35 m, silently. Now: refused, saying why."""
  x = codec.encode(np.array([100.0, 110.0, 119.0]), kitti)
  with pytest.raises(errors.InputError, match=f'x in {np.dtype(dtype).name}: too coarse'):
    codec.decode(np.asarray(x).astype(dtype), kitti)


@pytest.mark.parametrize('dtype', [np.float64, np.float32, np.float16, ml_dtypes.bfloat16])
def test_depth_error_through_each_accepted_dtype(kitti, dtype):
  """Metric depth at 1, 10, 80 and 120 m (and 119.9) in each dtype encode
  accepts: the code is float32 whatever came in, and decoding it loses no
  more than the input's own rounding plus 2e-5 of the depth. 120 m, the
  sensor's max, is a drop (valid is strictly inside the range); bfloat16
  rounds 119.9 m to 120 m, so it drops there too."""
  depths = np.array([1.0, 10.0, 80.0, 119.9, 120.0])
  given = depths.astype(dtype)
  x = codec.encode(given, kitti)
  assert x.dtype == jnp.float32
  got, valid = (np.asarray(v) for v in codec.decode(x, kitti))
  rounded = given.astype(np.float64)
  inside = (rounded > kitti.min_depth) & (rounded < kitti.max_depth)
  np.testing.assert_array_equal(valid, inside)
  assert not valid[-1]  # 120 m: a drop in every dtype
  err = np.abs(got - depths)[valid]
  bound = np.abs(rounded - depths)[valid] + 2e-5 * depths[valid]
  assert (err <= bound).all(), dict(zip(depths[valid], err))


# ----------------------------------------------------------------------------
# metrics
# ----------------------------------------------------------------------------


@pytest.fixture(scope='module')
def sets():
  rng = np.random.default_rng(5)
  real = rng.uniform(-0.9, 0.9, (4, 16, 64)).astype(np.float32)
  real[rng.uniform(size=real.shape) < 0.2] = ALPHA
  return real


@pytest.fixture(scope='module')
def angles():
  return tiny_sensor(16, 64).nominal_angles().astype(np.float32)


@pytest.mark.parametrize('bad', NON_FINITE)
def test_compare_refuses_non_finite_pixels(sets, angles, bad):
  """Issue row: NaN pixels gave finite JSD, COV, MMD, 1-NNA and a NaN SWD."""
  fake = sets[::-1].copy()
  fake[2, 3, 4] = bad
  with pytest.raises(errors.InputError, match=r'generated scans: 1 of .*\(2, 3, 4\).*ALPHA'):
    compare(sets, fake, angles, num_points=16)


@pytest.mark.parametrize('n', [0, -1, 2 ** 31, 16.0])
def test_compare_refuses_a_point_count_outside_int32(sets, angles, n):
  """Issue row: num_points=0 raised IndexError."""
  with pytest.raises(errors.InputError, match=rf'num_points={n!r}: must be a whole number >= 1'):
    compare(sets, sets, angles, num_points=n)


@pytest.mark.parametrize('n_real,n_fake', [(0, 0), (1, 1), (2, 3)])
def test_compare_refuses_empty_single_and_unpaired_sets(sets, angles, n_real, n_fake):
  """Empty sets raised ZeroDivisionError; one scan each failed in 1-NNA
  after the Chamfer matrices, unpaired ones in SWD after everything else."""
  more = np.concatenate([sets, sets])
  with pytest.raises(errors.InputError, match=f'got {n_real} real and {n_fake} generated'):
    compare(sets[:n_real], more[:n_fake], angles, num_points=16)


@pytest.mark.parametrize('dtype', HALF)
def test_compare_refuses_half_precision_scans(sets, angles, dtype):
  with pytest.raises(errors.InputError, match=f'real scans in {np.dtype(dtype).name}'):
    compare(sets.astype(dtype), sets, angles, num_points=16)


def test_compare_of_a_scan_without_a_return(sets, angles):
  """A generated scan of drops only has no cloud to sample: refused, named
  (reference protocol); the paper's clouds hold drops at the origin, as
  the authors' do, so it scores there, finite."""
  fake = sets[::-1].copy()
  fake[1] = ALPHA
  with pytest.raises(errors.InputError, match=r'clouds \[1\] have no valid point'):
    compare(sets, fake, angles, num_points=16)
  m = compare(sets, fake, angles, num_points=16, protocol='paper')
  assert all(np.isfinite(v) for v in m.values()), m


def test_identical_sets(sets, angles):
  """Issue row: identical sets gave 1-NNA 0 and SWD 0.066, unasserted. By the
  definitions: JSD 0, MMD 0 (to float32 rounding), COV 1 (each cloud its
  copy's nearest), 1-NNA 0 (each cloud's nearest is its copy, of the other
  set: the memorisation end, below the ideal 50%); SWD the sampling floor
  of PGGAN's estimator (each set draws its own patch positions): above 0,
  below a real difference, and falling as the patches grow in number."""
  m = compare(sets, sets.copy(), angles, num_points=16)
  mmd = m.pop('mmd')  # float32 rounding of |x|^2 - 2 x.y + |y|^2 for y = x
  assert 0 <= mmd < 1e-8
  floor = m.pop('swd')
  assert m == {'jsd': 0.0, 'cov': 1.0, '1nna': 0.0}
  assert floor == swd.swd(jax.random.key(0), sets, sets.copy())['swd_mean']  # seed 0
  smooth = scipy.ndimage.gaussian_filter(sets, (0, 2, 2))  # other structure, same size
  floors = [np.mean([swd.swd(jax.random.key(s), sets, sets, per_image=n)['swd_mean']
                     for s in range(3)]) for n in (16, 256)]
  other = np.mean([swd.swd(jax.random.key(s), sets, smooth,
                           per_image=256)['swd_mean'] for s in range(3)])
  assert 0 < floors[1] < floors[0] and floors[1] < other / 2, (floors, other)


@pytest.mark.parametrize('a,b', [(0.2, 0.2), (0.2, -0.5), (ALPHA, 1.0)])
def test_swd_of_constant_sets_is_zero(a, b):
  """Issue row: 63.98 against a constant 0.2 set, 63.58 between two
  constants: rounding residue over std + 1e-8. SWD compares each set's
  standardised patches, blind to level: a constant set normalises to 0."""
  shape = (4, 16, 64)
  got = swd.swd(jax.random.key(0), np.full(shape, a, np.float32), np.full(shape, b, np.float32),
                per_image=16)
  assert got['swd_mean'] == 0.0 and all(v == 0.0 for v in got.values())


@pytest.mark.parametrize('level', [0.0, 0.2, ALPHA])
def test_swd_of_a_constant_against_a_varying_set(level):
  """Zeros against standardised patches: the mean |projection| of the
  varying set's patches, the same whatever the constant, and about
  E|N(0, 1)| = 0.8 (each projection of unit variance)."""
  rng = np.random.default_rng(6)
  varying = rng.normal(size=(4, 16, 64)).astype(np.float32)
  constant = np.full_like(varying, level)
  got = swd.swd(jax.random.key(0), constant, varying, per_image=16)['swd_mean']
  zero = swd.swd(jax.random.key(0), np.zeros_like(varying), varying, per_image=16)['swd_mean']
  assert got == zero and 0.4 < got < 1.6


@pytest.mark.parametrize('bad', NON_FINITE)
def test_swd_refuses_non_finite_images(bad):
  a = np.zeros((2, 16, 64), np.float32)
  b = a.copy()
  b[1, 2, 3] = bad
  with pytest.raises(errors.InputError, match=r'images_b: 1 of 2048 .*\(1, 2, 3\)'):
    swd.swd(jax.random.key(0), a, b)
  with pytest.raises(errors.InputError, match='at least one image'):
    swd.swd(jax.random.key(0), a[:0], a[:0])


def test_one_nna_of_degenerate_sets():
  """Identical sets: 0 (the memorisation end); one cloud repeated in both
  sets: ties everywhere, a reference cloud wins each, so R is right and S
  wrong: n0 / (n0 + n1); too few clouds: refused with the counts."""
  rng = np.random.default_rng(7)
  clouds = rng.uniform(-0.5, 0.5, (5, 32, 3)).astype(np.float32)
  d = chamfer.pairwise(clouds)
  assert point_sets.one_nna(d, d, d) == 0.0
  zero = lambda n, m: np.zeros((n, m), np.float32)
  assert point_sets.one_nna(zero(3, 3), zero(3, 2), zero(2, 2)) == 3 / 5
  with pytest.raises(errors.InputError, match='got 1 and 1'):
    point_sets.one_nna(zero(1, 1), zero(1, 1), zero(1, 1))
  nan = d.copy()
  nan[0, 1] = np.nan
  with pytest.raises(errors.InputError, match='d_rs: 1 of 25'):
    point_sets.one_nna(d, nan, d)
  with pytest.raises(errors.InputError, match='Chamfer matrix'):
    point_sets.mmd_cov(nan)


def test_point_metrics_of_extreme_clouds():
  """Clouds at one point, at float32's largest, and with NaN: the Chamfer
  distance of equal clouds is 0; JSD of identical sets 0; NaN refused."""
  one = np.zeros((2, 8, 3), np.float32)
  assert (chamfer.pairwise(one) == 0).all()
  rng = np.random.default_rng(8)
  c = rng.uniform(-1, 1, (3, 16, 3)).astype(np.float32)
  assert point_sets.jsd(c, c) == 0.0
  far = np.full((1, 4, 3), 1e38, np.float32)  # beyond the grid: its edge
  assert np.isfinite(point_sets.jsd(far, c))
  bad = c.copy()
  bad[1, 2, 0] = np.nan
  with pytest.raises(errors.InputError, match=r'clouds_b: 1 of 144'):
    point_sets.jsd(c, bad)
  with pytest.raises(errors.InputError, match=r'clouds b: 1 of 144'):
    chamfer.pairwise(c, bad)


def test_depth_errors_at_the_ends_of_the_range(kitti):
  """Predictions of 0 (a drop: eps), the sensor's ends and 1e15 m against
  targets at the ends: finite, equal to the definitions in float64; NaN
  inside the mask refused, outside it ignored."""
  lo, hi = kitti.min_depth, kitti.max_depth
  target = np.array([[[lo, hi, lo, hi, 10.0]]], np.float32)
  pred = np.array([[[0.0, lo, hi, 1e15, np.nan]]], np.float32)
  mask = np.array([[[True, True, True, True, False]]])
  got = {k: float(v[0]) for k, v in depth.depth_errors(pred, target, mask).items()}
  p = np.maximum(pred[mask].astype(np.float64), 1e-6)
  t = target[mask].astype(np.float64)
  ratio = np.maximum(p / t, t / p)
  want = {'abs_rel': np.mean(np.abs(p - t) / t), 'sq_rel': np.mean((p - t) ** 2 / t),
          'rmse': np.sqrt(np.mean((p - t) ** 2)),
          'rmse_log': np.sqrt(np.mean((np.log(p) - np.log(t)) ** 2)),
          'delta1': np.mean(ratio < 1.25), 'delta2': np.mean(ratio < 1.25 ** 2),
          'delta3': np.mean(ratio < 1.25 ** 3), 'count': 4}
  assert all(np.isfinite(v) for v in got.values())
  for k, v in want.items():
    assert got[k] == pytest.approx(v, rel=1e-5), k
  with pytest.raises(errors.InputError, match='predicted depth inside the mask'):
    depth.depth_errors(pred, target, np.ones_like(mask))


@pytest.mark.parametrize('bad', [math.nan, math.inf, -0.1, 1.5])
def test_reliability_refuses_what_is_not_a_probability(bad):
  """Issue row: NaN predictions raised numpy's 'list argument must have no
  negative elements'; predictions outside [0, 1] gave ECE 4.5."""
  pred = np.array([0.1, bad, 0.9])
  with pytest.raises(errors.InputError, match='predictions'):
    calibration.reliability(pred, np.full(3, 0.5))
  with pytest.raises(errors.InputError, match='true probabilities'):
    calibration.reliability(np.full(3, 0.5), pred)


def test_reliability_at_exactly_0_and_1():
  """Predictions of exactly 0 and 1 fall in the first and last bins; ECE
  against an independent sum."""
  pred = np.array([0.0, 0.0, 1.0, 1.0])
  truth = np.array([0.0, 0.5, 1.0, 0.0])
  r = calibration.reliability(pred, truth, bins=4)
  assert r['count'].tolist() == [2, 0, 0, 2]
  assert r['ece'] == pytest.approx(0.5 * 0.25 + 0.5 * 0.5)


# ----------------------------------------------------------------------------
# levels.calibrate
# ----------------------------------------------------------------------------


@pytest.mark.parametrize('fill', [0.0, math.nan, 500.0])
def test_calibrate_refuses_scans_without_a_return(gen, fill):
  """Issue row: all-dropped or all-NaN scans gave offsets about -9.2 (the
  1e-4 keep floor), silently. Beyond the range (500 m) likewise."""
  depth = np.full((2, 16, 64), fill, np.float32)
  z = np.zeros((2, 16), np.float32)
  with pytest.raises(errors.InputError, match='none of the 2 scans has a return'):
    levels.calibrate(gen, depth, z, iterations=2)


@pytest.mark.parametrize('bad', NON_FINITE)
def test_calibrate_refuses_non_finite_latents(gen, bad):
  """Issue row: NaN latents gave all-zero offsets, no error."""
  depth = np.full((2, 16, 64), 20.0, np.float32)
  z = np.zeros((2, 16), np.float32)
  z[0, 1] = bad
  with pytest.raises(errors.InputError, match=r'latents: 1 of 32 .*\(0, 1\)'):
    levels.calibrate(gen, depth, z, iterations=2)


def test_calibrate_on_all_returned_and_half_precision_depth(gen):
  """Scans that return every pixel (keep 1, clipped to 1 - 1e-4) give
  finite offsets that raise the keep; a float16 copy of the depths (its
  rounding moves no pixel out of range) gives the same levels."""
  depth = np.random.default_rng(9).uniform(2, 100, (2, 16, 64)).astype(np.float32)
  z = np.asarray(jax.random.normal(jax.random.key(2), (2, 16)))
  got = levels.calibrate(gen, depth, z, iterations=8)
  table = np.asarray(got.variables['params']['depth_levels'])
  assert np.isfinite(table).all() and table.max() > 0
  half = levels.calibrate(gen, depth.astype(np.float16), z, iterations=8)
  np.testing.assert_array_equal(half.variables['params']['depth_levels'], table)


# ----------------------------------------------------------------------------
# configs.validate, the trainer's check
# ----------------------------------------------------------------------------


@pytest.mark.parametrize('field,value', [
    ('tau', 1e-45), ('tau', math.inf), ('tau', math.nan), ('tau', 0.009), ('tau', 101.0),
    ('ema_rampup', -0.1), ('ema_rampup', math.nan), ('ema_rampup', math.inf),
    ('ema_halflife_kimg', math.inf), ('ema_halflife_kimg', math.nan),
    ('ema_halflife_kimg', 1e9), ('ema_halflife_kimg', -1.0),
    ('lr', math.inf), ('lr', math.nan), ('r1_gamma', math.inf), ('adam_eps', math.inf),
    ('num_steps', 2 ** 31), ('batch_size', 2 ** 31)])
def test_validate_refuses_settings_that_cannot_train(field, value):
  """Issue row: tau 1e-45 or inf, ema_rampup < 0 or NaN and
  ema_halflife_kimg = inf were accepted; the EMA decay became 0, NaN or 1."""
  c = configs.default()
  c[field] = value
  with pytest.raises(configs.ConfigError, match=rf'config field {field}={value!r}: '):
    configs.validate(c)


@pytest.mark.parametrize('field,value', [
    ('tau', gumbel.TAU_RANGE[0]), ('tau', gumbel.TAU_RANGE[1]), ('ema_rampup', 0.0),
    ('ema_rampup', 1e30), ('ema_halflife_kimg', 0.0), ('r1_gamma', 0.0),
    ('num_steps', 2 ** 31 - 1)])
def test_validate_accepts_the_ends_of_each_range(field, value):
  c = configs.default()
  c[field] = value
  configs.validate(c)


def test_the_trainers_check_reads_the_ema_generator():
  """Issue row: the non-finite check read only the training metrics, so a
  NaN EMA generator went unnoticed. Now a NaN in its weights stops it."""
  finite = {'w': jnp.ones(3), 'b': jnp.zeros(2)}
  records = [(4, {'loss_d': 1.0, 'loss_g': 0.5})]
  trainer._check_finite(records, 2, finite)  # nothing to say
  with pytest.raises(trainer.NonFiniteLossError, match=r'at step 4: \{.*ema_params.*step 2'):
    trainer._check_finite(records, 2, {**finite, 'b': jnp.array([0.0, jnp.nan])})
  with pytest.raises(trainer.NonFiniteLossError, match=r"loss_g': inf"):
    trainer._check_finite([(1, {'loss_g': math.inf})], None, finite)
