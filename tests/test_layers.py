"""Convolutions: matmul and XLA paths against a brute-force definition."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dusty_jax import layers, models
from dusty_jax.sensor import get_sensor, tiny_sensor


def _np_cylinder_pad(x):
  x = np.concatenate([x[:, :, -1:], x, x[:, :, :1]], axis=2)
  return np.pad(x, ((0, 0), (1, 1), (0, 0), (0, 0)), mode='reflect')


def _np_conv_transpose(x, w, stride=2, pad=3):
  """PyTorch ConvTranspose2d semantics, by scattering each input pixel."""
  b, h, wd, cin = x.shape
  k = w.shape[0]
  full = np.zeros((b, (h - 1) * stride + k, (wd - 1) * stride + k, w.shape[3]))
  for i in range(h):
    for j in range(wd):
      full[:, i * stride:i * stride + k, j * stride:j * stride + k] += np.einsum(
          'bc,klco->bklo', x[:, i, j], w)
  return full[:, pad:full.shape[1] - pad, pad:full.shape[2] - pad]


def _np_conv(x, w, stride=2):
  b, h, wd, _ = x.shape
  k = w.shape[0]
  ho, wo = (h - k) // stride + 1, (wd - k) // stride + 1
  out = np.zeros((b, ho, wo, w.shape[3]))
  for i in range(ho):
    for j in range(wo):
      patch = x[:, i * stride:i * stride + k, j * stride:j * stride + k]
      out[:, i, j] = np.einsum('bklc,klco->bo', patch, w)
  return out


@pytest.fixture
def data():
  rng = np.random.default_rng(0)
  return (rng.normal(size=(2, 4, 8, 3)).astype(np.float32),
          rng.normal(size=(4, 4, 3, 5)).astype(np.float32))


@pytest.mark.parametrize('impl,tap_max_cin', [('matmul', layers.TAP_MAX_CIN),
                                               ('matmul', 0), ('xla', 0)])
def test_conv_up_matches_brute_force(data, impl, tap_max_cin, monkeypatch):
  # matmul: tap_conv (3 <= TAP_MAX_CIN input channels), and patches (0).
  monkeypatch.setattr(layers, 'TAP_MAX_CIN', tap_max_cin)
  x, w = data
  want = _np_conv_transpose(_np_cylinder_pad(x), w)
  got = layers.conv_up(jnp.asarray(x), jnp.asarray(w), impl)
  assert got.shape == (2, 8, 16, 5)
  np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize('impl', ['matmul', 'xla'])
def test_conv_up_few_outputs_col2im_matches_brute_force(impl):
  # Cout * COL2IM_RATIO <= Cin: the generator head's col2im path.
  rng = np.random.default_rng(1)
  x = rng.normal(size=(2, 4, 8, 16)).astype(np.float32)
  w = rng.normal(size=(4, 4, 16, 2)).astype(np.float32)
  assert 2 * layers.COL2IM_RATIO <= 16
  want = _np_conv_transpose(_np_cylinder_pad(x), w)
  got = layers.conv_up(jnp.asarray(x), jnp.asarray(w), impl)
  np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)
  # Its VJP is the adjoint of the brute-force map, in x and in w:
  # <ct, f(dx, w)> = <vjp_x(ct), dx>, <ct, f(x, dw)> = <vjp_w(ct), dw>.
  ct = rng.normal(size=want.shape).astype(np.float32)
  dx, dw = rng.normal(size=x.shape), rng.normal(size=w.shape)
  _, vjp = jax.vjp(lambda x, w: layers.conv_up(x, w, impl), jnp.asarray(x), jnp.asarray(w))
  gx, gw = vjp(jnp.asarray(ct))
  np.testing.assert_allclose(np.sum(gx * dx),
                             np.sum(ct * _np_conv_transpose(_np_cylinder_pad(dx), w)),
                             rtol=1e-4)
  np.testing.assert_allclose(np.sum(gw * dw),
                             np.sum(ct * _np_conv_transpose(_np_cylinder_pad(x), dw)),
                             rtol=1e-4)


def _plans(kind, x_shape, w_shape):
  """Every combination of forms of F, Dx and Dw a layer of this kind can take."""
  base = layers.plan(kind, x_shape, w_shape)
  dws = ('matmul', 'lax') + (('col2im',) if kind == 'up' and
                             w_shape[3] * layers.COL2IM_RATIO <= w_shape[2] else ())
  return [dataclasses.replace(base, f=f, dx=dx, dw=dw)
          for f in ('matmul', 'lax') for dx in ('matmul', 'lax') for dw in dws]


@pytest.mark.parametrize('kind,cin,cout', [('up', 3, 5), ('up', 16, 2), ('down', 3, 5)])
def test_every_plan_computes_the_same_map_to_second_order(kind, cin, cout):
  # Each of F, Dx, Dw in each form, against lax.conv differentiated by XLA:
  # the value, the VJP, and a second-order gradient (R1's kind) through it.
  rng = np.random.default_rng(3)
  x = jnp.asarray(rng.normal(size=(2, 6, 10, cin)), jnp.float32)
  # Outputs of order 1: sin and cos of larger ones amplify float32 rounding.
  w = jnp.asarray(rng.normal(size=(4, 4, cin, cout)) / np.sqrt(4 * cin), jnp.float32)
  ref = layers._up_lax if kind == 'up' else layers._down_lax
  y = ref(x, w)
  ct = jnp.asarray(rng.normal(size=y.shape), jnp.float32)

  def second(f):
    return jax.grad(lambda w: jnp.sum(jnp.sin(jax.grad(
        lambda x: jnp.sum(jnp.cos(f(x, w)) * ct))(x)) ** 2))(w)

  def second_x(f):  # through Dw: d/dx of a function of dL/dw
    return jax.grad(lambda x: jnp.sum(jnp.sin(jax.grad(
        lambda w: jnp.sum(jnp.cos(f(x, w)) * ct))(w)) ** 2))(x)

  want = (y, jax.vjp(ref, x, w)[1](ct), second(ref), second_x(ref))
  plans = _plans(kind, x.shape, w.shape)
  assert len(plans) >= 8
  for p in plans:
    f = lambda x, w, p=p: layers._conv(p, x, w)
    got = (f(x, w), jax.vjp(f, x, w)[1](ct), second(f), second_x(f))
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
      np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-4, err_msg=str(p))


def test_head_kernel_gradient_by_col2im_is_the_adjoint():
  # _up_col2im_dw(x, ct) = the transpose in w of the brute-force map.
  rng = np.random.default_rng(4)
  x = rng.normal(size=(2, 5, 7, 16)).astype(np.float32)
  ct = rng.normal(size=(2, 10, 14, 2)).astype(np.float32)
  v = rng.normal(size=(4, 4, 16, 2))
  xp = _np_cylinder_pad(x)
  gw = layers._up_col2im_dw(jnp.asarray(xp), jnp.asarray(ct))
  np.testing.assert_allclose(np.sum(gw * v), np.sum(ct * _np_conv_transpose(xp, v)),
                             rtol=1e-4)


def test_plan_follows_its_table():
  # The study's D: lax.conv for F and Dx, the paper's larger layers patches.
  study_d1 = layers.plan('down', (16, 34, 130, 16), (4, 4, 16, 32))
  paper_d1 = layers.plan('down', (32, 34, 130, 64), (4, 4, 64, 128))
  assert (study_d1.f, study_d1.dx, study_d1.dw) == ('lax', 'lax', 'lax')
  assert (paper_d1.f, paper_d1.dx, paper_d1.dw) == ('matmul', 'matmul', 'lax')
  assert layers.plan('down', (32, 18, 66, 128), (4, 4, 128, 256)).dw == 'matmul'
  # Heads: F by col2im, Dx by lax.conv, Dw by col2im; other up-convs matmuls.
  for cin in (16, 64):
    head = layers.plan('up', (16, 34, 130, cin), (4, 4, cin, 2))
    assert (head.f, head.dx, head.dw) == ('matmul', 'lax', 'col2im')
  assert layers.plan('up', (16, 18, 66, 32), (4, 4, 32, 16)).dx == 'matmul'


def test_tap_conv_vjp_is_the_adjoint_and_differentiates_again():
  rng = np.random.default_rng(2)
  x = rng.normal(size=(2, 5, 9, 3)).astype(np.float32)
  t = rng.normal(size=(2, 2, 3, 4)).astype(np.float32)
  def brute(x, t):
    return sum(np.einsum('bhwk,kn->bhwn', x[:, a:a + 4, b:b + 8], t[a, b])
               for a in range(2) for b in range(2))
  want = brute(x, t)
  np.testing.assert_allclose(layers.tap_conv(x, t), want, rtol=1e-5, atol=1e-5)
  # <ct, f(dx, t)> = <vjp_x(ct), dx> and <ct, f(x, dt)> = <vjp_t(ct), dt>.
  ct = rng.normal(size=want.shape)
  dx, dt = rng.normal(size=x.shape), rng.normal(size=t.shape)
  gx, gt = jax.vjp(layers.tap_conv, x, t)[1](jnp.asarray(ct, jnp.float32))
  np.testing.assert_allclose(np.sum(gx * dx), np.sum(ct * brute(dx, t)), rtol=1e-4)
  np.testing.assert_allclose(np.sum(gt * dt), np.sum(ct * brute(x, dt)), rtol=1e-4)
  # The VJP is itself differentiable (as R1's double backward needs of any
  # layer): against lax.conv, which computes the same map.
  ref = lambda x, t: jax.lax.conv_general_dilated(x, t, (1, 1), 'VALID',
                                                  dimension_numbers=('NHWC', 'HWIO', 'NHWC'))
  def second(f):
    return jax.grad(lambda t: jnp.sum(jnp.sin(jax.grad(
        lambda x: jnp.sum(jnp.cos(f(x, t))))(x)) ** 2))(t)
  np.testing.assert_allclose(second(layers.tap_conv), second(ref), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize('impl', ['matmul', 'xla'])
def test_conv_down_matches_brute_force(data, impl):
  x, w = data
  want = _np_conv(_np_cylinder_pad(x), w)
  got = layers.conv_down(jnp.asarray(x), jnp.asarray(w), impl)
  assert got.shape == (2, 2, 4, 5)
  np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


def test_circular_shift_equivariance(data):
  x, w = data
  up = lambda v: layers.conv_up(v, w, 'matmul')
  np.testing.assert_allclose(up(jnp.roll(x, 1, axis=2)), jnp.roll(up(x), 2, axis=2),
                             rtol=1e-5, atol=1e-5)
  down = lambda v: layers.conv_down(v, w, 'matmul')
  x8 = np.concatenate([x, x], axis=2)
  np.testing.assert_allclose(down(jnp.roll(x8, 2, axis=2)),
                             jnp.roll(down(x8), 1, axis=2), rtol=1e-5, atol=1e-5)
  blur = layers.blur_vh(jnp.asarray(x))
  np.testing.assert_allclose(layers.blur_vh(jnp.roll(x, 3, axis=2)),
                             jnp.roll(blur, 3, axis=2), rtol=1e-6)


def test_impls_agree_including_r1_double_backward():
  s = tiny_sensor(16, 64)
  outs = {}
  for impl in ('matmul', 'xla'):
    m = models.ModelSettings('dusty2', latent_dim=16, ch_base=4, ch_max=16)
    g, d = m.generator(s, impl), m.discriminator(s, impl)
    z = jax.random.normal(jax.random.key(0), (2, 16))
    gp = jax.jit(g.init)(jax.random.key(1), z)
    x = jnp.tanh(jax.jit(g.apply)(gp, z)[..., 0])
    dp = jax.jit(d.init)(jax.random.key(2), x)

    def r1(dp):
      grad = jax.grad(lambda x: d.apply(dp, x).sum())(x)
      return jnp.sum(grad ** 2)
    outs[impl] = (x, jax.jit(d.apply)(dp, x), jax.jit(jax.grad(r1))(dp))
  for a, b in zip(jax.tree.leaves(outs['matmul']), jax.tree.leaves(outs['xla'])):
    np.testing.assert_allclose(a, b, rtol=2e-3, atol=1e-4)


@pytest.mark.parametrize('preset, shape', [('kitti', (64, 256)), ('mpo', (32, 256))])
def test_shapes_derive_from_sensor(preset, shape):
  s = get_sensor(preset)
  m = models.ModelSettings('dusty1', latent_dim=8, ch_base=2, ch_max=4)
  g, d = m.generator(s), m.discriminator(s)
  z = jnp.zeros((1, 8))
  gp = jax.eval_shape(g.init, jax.random.key(0), z)
  assert gp['params']['proj'].shape == (8, shape[0] // 16 * shape[1] // 16 * 4)
  out = jax.eval_shape(g.apply, gp, z)
  assert out.shape == (1,) + shape + (2,)
  dp = jax.eval_shape(d.init, jax.random.key(0), jnp.zeros((1,) + shape))
  assert dp['params']['out'].shape == (shape[0] // 16 * shape[1] // 16 * 4, 1)


def test_bad_sensor_shape():
  # Any number of rows (tests/test_beam_counts.py); a width must be a multiple of 16.
  with pytest.raises(ValueError, match='16x70; the nearest valid width is 64'):
    models.ModelSettings('dusty1').discriminator(tiny_sensor(16, 70))
  with pytest.raises(ValueError, match="unknown model 'dusty3'"):
    models.ModelSettings('dusty3')
