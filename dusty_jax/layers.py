"""Cylinder-aware convolutions with equalized learning rate.

A range image is a cylinder: every convolution pads horizontally by wrapping
around and vertically by reflection. Tensors are NHWC.

Two implementations of each convolution, chosen per backend (``impl``):
  * ``'matmul'``: patches gathered with slices, then one matrix product. On
    the CPU, XLA's convolution gradients (and the double-backward of the R1
    penalty) are several times slower than matmuls of the same size; written
    this way, forward, backward and double-backward are all plain matmuls.
    Exceptions, measured: the generator's head (few output channels)
    takes its gradient from ``lax.conv`` (``_up_few``), and its up-convs of
    at most TAP_MAX_CIN input channels sum four shifted matmuls
    (``tap_conv``) instead of gathering patches.
  * ``'xla'``: ``lax.conv_general_dilated``, which maps to cuDNN on a GPU.
Both compute the same function; tests check they agree.
"""

from __future__ import annotations

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


def conv_down(x, w, impl: str):
  """4x4 stride-2 convolution after a 1-pixel cylinder pad: (H, W) -> (H/2, W/2).

  ``w``: (4, 4, Cin, Cout), already scaled.
  """
  x = cylinder_pad(x, 1, 1, 1, 1)
  if impl == 'xla':
    return lax.conv_general_dilated(x, w, (2, 2), 'VALID',
                                    dimension_numbers=('NHWC', 'HWIO', 'NHWC'))
  # A 4x4 stride-2 conv is a 2x2 stride-1 conv of the space-to-depth input.
  cin, cout = w.shape[2], w.shape[3]
  w_s2d = w.reshape(2, 2, 2, 2, cin, cout).transpose(0, 2, 1, 3, 4, 5)
  w_s2d = w_s2d.reshape(2 * 2 * 4 * cin, cout)  # (a, b, di, dj, c)
  return _matmul(_patches(space_to_depth(x), 2, 2), w_s2d)


# conv_up uses col2im when Cout * COL2IM_RATIO <= Cin, im2col otherwise.
COL2IM_RATIO = 8
# ... and, for im2col, the four-tap form (tap_conv) when Cin <= TAP_MAX_CIN.
# Measured on a 2-core EPYC (benchmarks/step_phases.py): at the CPU study's
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
  x = cylinder_pad(x, 1, 1, 1, 1)
  b, hp, wp, _ = x.shape
  h, wd = hp - 2, wp - 2
  cout = w.shape[3]
  if impl == 'xla':
    return _up_lax(x, w)
  if cout * COL2IM_RATIO > w.shape[2]:
    # im2col: per output phase, the 2x2 taps of the padded input times the
    # phase's kernel taps, by tap_conv or by patches (4 * Cin) and one
    # matmul. Forward and backward are plain matmuls.
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
  # col2im, for few output channels (the generator's head); see _up_few.
  return _up_few(x, w)


def _up_lax(x, w):
  """conv_up of an already padded input by ``lax.conv_general_dilated``: a
  transposed conv is a conv of the 2-dilated input with the flipped kernel."""
  h, wd = x.shape[1] - 2, x.shape[2] - 2
  return lax.conv_general_dilated(
      x, w[::-1, ::-1], (1, 1), ((0, 0), (0, 0)), lhs_dilation=(2, 2),
      dimension_numbers=('NHWC', 'HWIO', 'NHWC'))[:, :2 * h, :2 * wd]


@jax.custom_vjp
def _up_few(x, w):
  """conv_up of an already padded input with few output channels (the
  generator's head), by col2im: every input pixel's contribution to all 16
  taps in one matmul (Cin -> 16 * Cout, far smaller than 16 * Cin of
  patches), then each output phase adds four shifted slices. The cylinder
  pad commutes with the per-pixel matmul, so it is applied to the product.

  Its gradient is lax.conv's (_up_lax, the same linear map): the transpose
  of the strided slices of a (.., 4, 4, Cout) tensor with Cout = 2 is slow
  on XLA's CPU backend (measured on a 2-core EPYC at the study's scale:
  the head's VJP took 296 ms by col2im, 33 ms so; benchmarks/step_phases.py),
  while the forward pass, all that sampling needs, is faster by col2im (3
  ms against 8)."""
  b, hp, wp, _ = x.shape
  h, wd = hp - 2, wp - 2
  cout = w.shape[3]
  x = x[:, 1:-1, 1:-1]
  z = _matmul(x, w.transpose(2, 0, 1, 3).reshape(w.shape[2], 16 * cout))
  z = cylinder_pad(z, 1, 1, 1, 1).reshape(b, hp, wp, 4, 4, cout)
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


def _up_few_fwd(x, w):
  return _up_few(x, w), (x, w)


def _up_few_bwd(residuals, cotangent):
  # conv_up is linear in x and in w: under jit the forward pass that vjp
  # traces is unused and removed.
  return jax.vjp(_up_lax, *residuals)[1](cotangent)


_up_few.defvjp(_up_few_fwd, _up_few_bwd)


def blur_vh(x):
  """Fixed [1, 2, 1]/4 vertical and horizontal blurs, stacked as channels."""
  v = cylinder_pad(x, 1, 1, 0, 0)
  v = 0.25 * v[:, :-2] + 0.5 * v[:, 1:-1] + 0.25 * v[:, 2:]
  h = cylinder_pad(x, 0, 0, 1, 1)
  h = 0.25 * h[:, :, :-2] + 0.5 * h[:, :, 1:-1] + 0.25 * h[:, :, 2:]
  return jnp.concatenate([v, h], axis=-1)
