"""Cylinder-aware convolutions with equalized learning rate.

A range image is a cylinder: every convolution pads horizontally by wrapping
around and vertically by reflection. Tensors are NHWC.

Two implementations of each convolution, chosen per backend (``impl``):
  * ``'matmul'``, the CPU's: a layer is three linear maps, the conv ``F(x,
    w)`` and its transposes in ``x`` (``Dx``) and in ``w`` (``Dw``), and the
    VJP of each is two of the others, to every order (R1's double backward
    included). Each of the three is computed in the form measured fastest on
    the CPU for the layer's size (``plan``): patches gathered with slices
    and one matrix product, four shifted matmuls (``tap_conv``), col2im for
    the generator's head, or ``lax.conv``. XLA's CPU convolution gradients
    are in places many times slower than matmuls of the same size, and
    elsewhere faster: one form for the whole layer loses either way.
  * ``'xla'``: ``lax.conv_general_dilated`` differentiated by XLA, which maps
    to cuDNN on a GPU.
Both compute the same function; tests check they agree.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from jax import lax

LEAKY_SLOPE = 0.2
ACT_GAIN = math.sqrt(2.0)  # He gain of leaky ReLU, applied after activation.


def default_impl() -> str:
  return 'matmul' if jax.default_backend() == 'cpu' else 'xla'


def cylinder_pad(x, top: int, bottom: int, left: int, right: int):
  """Pads NHWC: wraps horizontally (the scan is a cylinder), reflects vertically."""
  if left or right:
    w = x.shape[2]
    parts = []
    if left:
      parts.append(x[:, :, w - left:])
    parts.append(x)
    if right:
      parts.append(x[:, :, :right])
    x = jnp.concatenate(parts, axis=2)
  if top or bottom:
    x = jnp.pad(x, ((0, 0), (top, bottom), (0, 0), (0, 0)), mode='reflect')
  return x


def leaky_act(x, bias):
  """Bias, leaky ReLU 0.2 and the sqrt(2) gain (the authors' FusedLeakyReLU)."""
  return jax.nn.leaky_relu(x + bias, LEAKY_SLOPE) * ACT_GAIN


def _patches(x, kh: int, kw: int):
  """(B, H, W, C) -> (B, H-kh+1, W-kw+1, kh*kw*C), taps in (i, j, c) order."""
  _, h, w, _ = x.shape
  ho, wo = h - kh + 1, w - kw + 1
  cols = [x[:, i:i + ho, j:j + wo, :] for i in range(kh) for j in range(kw)]
  return jnp.concatenate(cols, axis=-1)


def _matmul(p, w2d):
  return lax.dot_general(p, w2d, (((p.ndim - 1,), (0,)), ((), ())))


def space_to_depth(x):
  """(B, 2h, 2w, C) -> (B, h, w, 4C), channels in (di, dj, c) order."""
  b, h, w, c = x.shape
  x = x.reshape(b, h // 2, 2, w // 2, 2, c).transpose(0, 1, 3, 2, 4, 5)
  return x.reshape(b, h // 2, w // 2, 4 * c)


def _promote(x, w):
  """x and w in one dtype, as lax.conv requires (matmuls would promote)."""
  dtype = jnp.result_type(x, w)
  return x.astype(dtype), w.astype(dtype)


def conv_down(x, w, impl: str):
  """4x4 stride-2 convolution after a 1-pixel cylinder pad: (H, W) -> (H/2, W/2).

  ``w``: (4, 4, Cin, Cout), already scaled.
  """
  x, w = _promote(cylinder_pad(x, 1, 1, 1, 1), w)
  if impl == 'xla':
    return _down_lax(x, w)
  return _conv(plan('down', x.shape, w.shape), x, w)


def _down_lax(x, w):
  return lax.conv_general_dilated(x, w, (2, 2), 'VALID',
                                  dimension_numbers=('NHWC', 'HWIO', 'NHWC'))


def _down_matmul(x, w):
  # A 4x4 stride-2 conv is a 2x2 stride-1 conv of the space-to-depth input.
  cin, cout = w.shape[2], w.shape[3]
  w_s2d = w.reshape(2, 2, 2, 2, cin, cout).transpose(0, 2, 1, 3, 4, 5)
  w_s2d = w_s2d.reshape(2 * 2 * 4 * cin, cout)  # (a, b, di, dj, c)
  return _matmul(_patches(space_to_depth(x), 2, 2), w_s2d)


# conv_up uses col2im when Cout * COL2IM_RATIO <= Cin, im2col otherwise.
COL2IM_RATIO = 8
# ... and, for im2col, the four-tap form (tap_conv) when Cin <= TAP_MAX_CIN.
# Measured on a 2-core EPYC (benchmarks/research/speed/step_phases.py): at the CPU study's
# sizes (Cin 32..128) the generator's VJP takes 0.8x the time of patches and
# its forward 0.4x; at the paper's Cin of 256 and 512 the two are even.
TAP_MAX_CIN = 128


def _tap_sum(x, t):
  ho, wo = x.shape[1] - 1, x.shape[2] - 1
  return sum(_matmul(x[:, a:a + ho, b:b + wo], t[a, b]) for a in range(2) for b in range(2))


@jax.custom_vjp
def tap_conv(x, t):
  """A 2x2 valid convolution as the sum of four matmuls of shifted views:
  (B, H+1, W+1, K), taps (2, 2, K, N) -> (B, H, W, N), out[i, j] =
  sum_ab x[i+a, j+b] @ t[a, b]. XLA's CPU backend fuses the slices into the
  matmuls, where patches would copy the input four times.

  Its VJP keeps that form: the input's gradient is the same map on the
  padded cotangent with the taps flipped and transposed, the taps' gradient
  one contraction per tap. Autodiff of the forward would instead pad four
  (B, H+1, W+1, K) products."""
  return _tap_sum(x, t)


def _tap_conv_fwd(x, t):
  return tap_conv(x, t), (x, t)


def _tap_conv_bwd(residuals, ct):
  x, t = residuals
  ho, wo = ct.shape[1], ct.shape[2]
  dx = tap_conv(jnp.pad(ct, ((0, 0), (1, 1), (1, 1), (0, 0))),
                jnp.swapaxes(t[::-1, ::-1], 2, 3))
  over_pixels = (((0, 1, 2), (0, 1, 2)), ((), ()))
  dt = jnp.stack([jnp.stack([lax.dot_general(x[:, a:a + ho, b:b + wo], ct, over_pixels)
                             for b in range(2)]) for a in range(2)])
  return dx, dt


tap_conv.defvjp(_tap_conv_fwd, _tap_conv_bwd)

# For output phase r of the stride-2 transposed conv (padding 3 after a
# 1-pixel pad), the two input taps at offsets r, r+1 use kernel rows:
_UP_TAPS = ((3, 1), (2, 0))


def conv_up(x, w, impl: str):
  """4x4 stride-2 transposed conv after a 1-pixel cylinder pad: (H, W) -> (2H, 2W).

  The authors' ``ConvTranspose2d(k=4, s=2, p=3)`` on a padded input. ``w``:
  (4, 4, Cin, Cout), already scaled, indexed as PyTorch's transposed kernel.
  """
  x, w = _promote(cylinder_pad(x, 1, 1, 1, 1), w)
  if impl == 'xla':
    return _up_lax(x, w)
  return _conv(plan('up', x.shape, w.shape), x, w)


def _up_matmul(x, w):
  """conv_up of an already padded input by matmuls: im2col (tap_conv or
  patches), or col2im for few output channels (the generator's head)."""
  b, hp, wp, _ = x.shape
  h, wd = hp - 2, wp - 2
  cout = w.shape[3]
  if cout * COL2IM_RATIO <= w.shape[2]:
    return _up_col2im(x, w)
  # im2col: per output phase, the 2x2 taps of the padded input times the
  # phase's kernel taps, by tap_conv or by patches (4 * Cin) and one matmul.
  phases = []
  for ry in range(2):
    row = []
    for rx in range(2):
      taps = jnp.stack([jnp.stack([w[a, c] for c in _UP_TAPS[rx]])
                        for a in _UP_TAPS[ry]])
      window = x[:, ry:ry + h + 1, rx:rx + wd + 1]
      if w.shape[2] <= TAP_MAX_CIN:
        row.append(tap_conv(window, taps))
      else:
        row.append(_matmul(_patches(window, 2, 2), taps.reshape(-1, cout)))
    phases.append(jnp.stack(row, axis=3))  # (B, h, w, 2[rx], C)
  y = jnp.stack(phases, axis=2)  # (B, h, 2[ry], w, 2[rx], C)
  return y.reshape(b, 2 * h, 2 * wd, cout)


def _up_lax(x, w):
  """conv_up of an already padded input by ``lax.conv_general_dilated``: a
  transposed conv is a conv of the 2-dilated input with the flipped kernel."""
  h, wd = x.shape[1] - 2, x.shape[2] - 2
  return lax.conv_general_dilated(
      x, w[::-1, ::-1], (1, 1), ((0, 0), (0, 0)), lhs_dilation=(2, 2),
      dimension_numbers=('NHWC', 'HWIO', 'NHWC'))[:, :2 * h, :2 * wd]


def _up_col2im(x, w):
  """conv_up of an already padded input with few output channels, by
  col2im: every input pixel's contribution to all 16 taps in one matmul
  (Cin -> 16 * Cout, far smaller than 16 * Cin of patches), then each output
  phase adds four shifted slices."""
  b, hp, wp, _ = x.shape
  h, wd = hp - 2, wp - 2
  cout = w.shape[3]
  z = _matmul(x, w.transpose(2, 0, 1, 3).reshape(w.shape[2], 16 * cout))
  z = z.reshape(b, hp, wp, 4, 4, cout)
  phases = []
  for ry in range(2):
    row = []
    for rx in range(2):
      acc = 0.0
      for dy in range(2):
        for dx in range(2):
          acc = acc + z[:, ry + dy:ry + dy + h, rx + dx:rx + dx + wd,
                        _UP_TAPS[ry][dy], _UP_TAPS[rx][dx]]
      row.append(acc)
    phases.append(jnp.stack(row, axis=3))  # (B, h, w, 2[rx], C)
  y = jnp.stack(phases, axis=2)  # (B, h, 2[ry], w, 2[rx], C)
  return y.reshape(b, 2 * h, 2 * wd, cout)


def _up_col2im_dw(x, ct):
  """Dw of conv_up (the transpose in the kernel) for few output channels:
  the cotangent of col2im's product, (B, H+2, W+2, 16 * Cout), is each output
  phase's cotangent placed at its tap's offset, and Dw is one matmul of the
  padded input with it. XLA's own kernel gradient of this layer, by either
  form, contracts 2 output channels over every pixel at a few GFLOP/s."""
  b, hp, wp, cin = x.shape
  h, wd = hp - 2, wp - 2
  cout = ct.shape[-1]
  ct = ct.reshape(b, h, 2, wd, 2, cout)
  parts = []
  for ky in range(4):
    ry, dy = _UP_PHASE[ky]
    for kx in range(4):
      rx, dx = _UP_PHASE[kx]
      u, v = ry + dy, rx + dx
      parts.append(jnp.pad(ct[:, :, ry, :, rx], ((0, 0), (u, 2 - u), (v, 2 - v), (0, 0))))
  dz = jnp.stack(parts, axis=3).reshape(-1, 16 * cout)
  dw = lax.dot_general(x.reshape(-1, cin), dz, (((0,), (0,)), ((), ())))
  return dw.reshape(cin, 4, 4, cout).transpose(1, 2, 0, 3)


# Kernel row (or column) k -> (output phase r, tap d) with _UP_TAPS[r][d] == k.
_UP_PHASE = {k: (r, d) for r in range(2) for d, k in enumerate(_UP_TAPS[r])}


# Which form computes each linear map of a 'matmul' layer: by the per-layer
# timings of each map in each form on a 2-core EPYC, at the CPU study's and
# the paper's sizes, and by whole gradients under variants of this plan
# (python benchmarks/research/speed/conv_forms.py --graphs,
# benchmarks/research/speed/results/conv_forms_cpu.json, medians of 3 rounds):
#  * down-convs: F and Dx by lax.conv while the layer's batch * Cin * Cout *
#    Ho * Wo <= DOWN_SMALL_MAX (the study's D), by patches above (the
#    paper's, where lax.conv's F was up to 1.8x slower). Alone, the study
#    layers' F was up to 1.4x faster by lax.conv and their Dx as fast or
#    faster by patches, but with the patches' Dx D's loss gradient took
#    1.17x as long and R1 1.4x. Dw by lax.conv while Cin <=
#    DOWN_DW_LAX_MAX_CIN (1.4-3.9x faster), patches above.
#  * up-convs: F by im2col, a head (few outputs) by col2im (never slower
#    than lax.conv, 4x faster for the study's head); Dx by the matmuls'
#    transpose, for a head by lax.conv (a forward strided conv of the
#    cotangent, 2-4.6x faster). Alone, lax.conv's Dx was also up to 2x
#    faster for the other up-convs of <= 256 inputs, but inside inversion's
#    gradient (vmapped, in a loop) it made inversion 1.9x (paper, batch 8)
#    to 3.5x (study, batch 32) slower. Dw by the matmuls' transpose
#    (lax.conv's took 20x as long), for a head by _up_col2im_dw (7-14x
#    faster than lax.conv's, 2.6-4.6x than autodiff's of col2im).
DOWN_SMALL_MAX = 2**23
DOWN_DW_LAX_MAX_CIN = 64


@dataclasses.dataclass(frozen=True)
class Plan:
  """How a 'matmul' layer computes its three linear maps: ``kind`` ('up' or
  'down'), the padded input's and the kernel's shapes, and one form of each
  map: 'matmul' (the matmul forward, or its transpose by autodiff), 'lax'
  (lax.conv's), or 'col2im' (Dw of a head, _up_col2im_dw)."""
  kind: str
  x_shape: tuple
  w_shape: tuple
  f: str
  dx: str
  dw: str


def plan(kind: str, x_shape, w_shape) -> Plan:
  """The forms of a layer's F, Dx and Dw (see the table above)."""
  x_shape, w_shape = tuple(x_shape), tuple(w_shape)
  cin, cout = w_shape[2], w_shape[3]
  if kind == 'down':
    b, ho, wo = x_shape[0], (x_shape[1] - 2) // 2, (x_shape[2] - 2) // 2
    small = b * cin * cout * ho * wo <= DOWN_SMALL_MAX
    dw = 'lax' if cin <= DOWN_DW_LAX_MAX_CIN else 'matmul'
    return Plan(kind, x_shape, w_shape, *(['lax'] * 2 if small else ['matmul'] * 2), dw)
  head = cout * COL2IM_RATIO <= cin
  if head:
    return Plan(kind, x_shape, w_shape, 'matmul', 'lax', 'col2im')
  return Plan(kind, x_shape, w_shape, 'matmul', 'matmul', 'matmul')


def _forward(kind: str, form: str):
  return {('down', 'matmul'): _down_matmul, ('down', 'lax'): _down_lax,
          ('up', 'matmul'): _up_matmul, ('up', 'lax'): _up_lax}[kind, form]


def _apply_f(p: Plan, x, w):
  return _forward(p.kind, p.f)(x, w)


def _varying_axes(a) -> frozenset:
  t = jax.typeof(a)
  vma = getattr(t, 'vma', None)  # its name in later JAX versions
  if vma is None:
    vma = getattr(getattr(t, 'manual_axis_type', None), 'varying', frozenset())
  return vma


def _zeros(shape, *like):
  """Zeros at which to take a linear map's VJP, varying over the same
  shard_map axes as ``like``: a primal that did not vary would have its
  cotangent summed over the devices."""
  z = jnp.zeros(shape, like[0].dtype)
  axes = set().union(*(_varying_axes(a) for a in like))
  return lax.pcast(z, tuple(sorted(axes)), to='varying') if axes else z


def _apply_dx(p: Plan, ct, w):
  f = _forward(p.kind, p.dx)
  # F is linear in x: jit removes the forward pass on zeros that vjp traces.
  return jax.vjp(lambda x: f(x, w), _zeros(p.x_shape, ct, w))[1](ct)[0]


def _apply_dw(p: Plan, x, ct):
  if p.dw == 'col2im':
    return _up_col2im_dw(x, ct)
  f = _forward(p.kind, p.dw)
  return jax.vjp(lambda w: f(x, w), _zeros(p.w_shape, x, ct))[1](ct)[0]


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _conv(p: Plan, x, w):
  """F(x, w) of a padded input; its VJP is (Dx(ct, w), Dw(x, ct))."""
  return _apply_f(p, x, w)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _conv_dx(p: Plan, ct, w):
  """Dx(ct, w), the transpose of F in x; its VJP in (ct, w) for a cotangent
  g shaped like x: (F(g, w), Dw(g, ct))."""
  return _apply_dx(p, ct, w)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _conv_dw(p: Plan, x, ct):
  """Dw(x, ct), the transpose of F in w; its VJP in (x, ct) for a cotangent
  v shaped like w: (Dx(ct, v), F(x, v))."""
  return _apply_dw(p, x, ct)


_conv.defvjp(lambda p, x, w: (_conv(p, x, w), (x, w)),
             lambda p, r, ct: (_conv_dx(p, ct, r[1]), _conv_dw(p, r[0], ct)))
_conv_dx.defvjp(lambda p, ct, w: (_conv_dx(p, ct, w), (ct, w)),
                lambda p, r, g: (_conv(p, g, r[1]), _conv_dw(p, g, r[0])))
_conv_dw.defvjp(lambda p, x, ct: (_conv_dw(p, x, ct), (x, ct)),
                lambda p, r, v: (_conv_dx(p, r[1], v), _conv(p, r[0], v)))


def blur_vh(x):
  """Fixed [1, 2, 1]/4 vertical and horizontal blurs, stacked as channels."""
  v = cylinder_pad(x, 1, 1, 0, 0)
  v = 0.25 * v[:, :-2] + 0.5 * v[:, 1:-1] + 0.25 * v[:, 2:]
  h = cylinder_pad(x, 0, 0, 1, 1)
  h = 0.25 * h[:, :, :-2] + 0.5 * h[:, :, 1:-1] + 0.25 * h[:, :, 2:]
  return jnp.concatenate([v, h], axis=-1)
