"""Each conv layer's three linear maps, timed in each form they can take.

    python benchmarks/research/speed/conv_forms.py [--scales study,paper] [--rounds 3] [--graphs]

A 'matmul' conv layer (dusty_jax/layers.py) is three linear maps: the conv
F(x, w), its transpose in the input Dx(ct, w) and in the kernel Dw(x, ct).
Training needs all three (R1 differentiates D twice), and each can be
computed by the matmul forward (or autodiff's transpose of it), by
lax.conv's, or for a head's Dw by col2im. This times every form of every map
for each of the generator's and the discriminator's layers, at the CPU
study's size (DUSty-I, latent 128, channels 16..128, batch 16) and the
paper's (channels 64..512, batch 32), and marks the form ``layers.plan``
picks. Rounds alternate the forms, medians of the rounds are printed.

Alone, a map can time differently than inside a whole gradient, where XLA
fuses and schedules it with its neighbours. With ``--graphs`` it also times,
at the study's size, the gradients a training step takes (G's VJP, D's loss
gradient, R1's double backward, G's loss gradient through D) under the plan
and under variants of it (VARIANTS; 'before' is the forms of the previous
release: patches and tap matmuls throughout, the head's gradient from
lax.conv).

Writes benchmarks/research/speed/results/conv_forms_cpu.json.
"""

import argparse
import dataclasses
import os
import statistics
import sys

import jax
import jax.numpy as jnp

# benchmarks/ holds common.py, shared with the product benchmarks.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..'))
import common
from dusty_jax import layers

HERE = os.path.dirname(os.path.abspath(__file__))
# (batch, [(H, W, Cin, Cout) of each up-conv's input], [... of each down-conv's])
SCALES = {
    'study': (16, [(4, 16, 128, 64), (8, 32, 64, 32), (16, 64, 32, 16), (32, 128, 16, 2)],
              [(64, 256, 2, 16), (32, 128, 16, 32), (16, 64, 32, 64), (8, 32, 64, 128)]),
    'paper': (32, [(4, 16, 512, 256), (8, 32, 256, 128), (16, 64, 128, 64), (32, 128, 64, 2)],
              [(64, 256, 2, 64), (32, 128, 64, 128), (16, 64, 128, 256), (8, 32, 256, 512)]),
}
FORMS = {'f': ('matmul', 'lax'), 'dx': ('matmul', 'lax'), 'dw': ('matmul', 'lax', 'col2im')}


def _before(p):
  if p.kind == 'down':
    return dataclasses.replace(p, f='matmul', dx='matmul', dw='matmul')
  head = p.dw == 'col2im'
  return dataclasses.replace(p, f='matmul', dx='lax' if head else 'matmul',
                             dw='lax' if head else 'matmul')


# name -> a Plan rewrite.
VARIANTS = {
    'plan': lambda p: p,
    'down_dx_matmul': lambda p: dataclasses.replace(p, dx='matmul') if p.kind == 'down' else p,
    # lax.conv's Dx for the up-convs of <= 256 inputs: faster alone, and
    # inside the training step, but 1.9-3.5x slower in inversion.
    'up_dx_lax': lambda p: (dataclasses.replace(p, dx='lax')
                            if p.kind == 'up' and p.w_shape[2] <= 256 else p),
    'before': _before,
}


def layer_cases(kind, b, h, w, cin, cout):
  """{(map, form): (jitted fn, args)} of one layer."""
  key = jax.random.key(0)
  x = layers.cylinder_pad(jax.random.normal(key, (b, h, w, cin)), 1, 1, 1, 1)
  wt = jax.random.normal(key, (4, 4, cin, cout)) * 0.1
  base = layers.plan(kind, x.shape, wt.shape)
  ct = jax.random.normal(key, jax.eval_shape(lambda: layers._apply_f(base, x, wt)).shape)
  cases = {}
  for m, forms in FORMS.items():
    for form in forms:
      if form == 'col2im' and not (kind == 'up' and cout * layers.COL2IM_RATIO <= cin):
        continue
      p = dataclasses.replace(base, **{m: form})
      fn, args = {'f': (layers._apply_f, (x, wt)), 'dx': (layers._apply_dx, (ct, wt)),
                  'dw': (layers._apply_dw, (x, ct))}[m]
      cases[m, form] = (jax.jit(lambda *a, p=p, fn=fn: fn(p, *a)), args)
  return base, cases


def time_layer(cases, rounds, budget_s=1.0):
  times = {k: [] for k in cases}
  for k, (fn, args) in cases.items():  # compile and warm up
    jax.block_until_ready(fn(*args))
  for _ in range(rounds):
    for k, (fn, args) in cases.items():
      once = common.seconds(lambda: fn(*args))[0]
      reps = 1 if once > budget_s else 5
      times[k].append(once if reps == 1 else common.timed(lambda: fn(*args), reps, 0).median)
  return {k: statistics.median(v) for k, v in times.items()}


def time_graphs(rounds):
  """{(gradient, variant): median ms} at the study's size."""
  from dusty_jax import models
  from dusty_jax.sensor import get_sensor
  sensor = get_sensor('kitti')
  m = models.ModelSettings('dusty1', latent_dim=128, ch_base=16, ch_max=128)
  g, d = m.generator(sensor, 'matmul'), m.discriminator(sensor, 'matmul')
  z = jax.random.normal(jax.random.key(1), (16, 128))
  gp = g.init(jax.random.key(0), z)
  x = jnp.tanh(g.apply(gp, z)[..., 0])
  dp = d.init(jax.random.key(2), x)
  graphs = {
      'g_vjp': (lambda p: jax.vjp(lambda p: g.apply(p, z), p)[1](jnp.ones_like(x)[..., None].repeat(2, -1)), gp),
      'd_grad': (lambda p: jax.grad(lambda p: d.apply(p, x).sum() - d.apply(p, x[::-1]).sum())(p), dp),
      'r1': (lambda p: jax.grad(lambda p: jnp.sum(jax.grad(lambda x: d.apply(p, x).sum())(x) ** 2))(p), dp),
      'g_through_d': (lambda p: jax.grad(
          lambda p: d.apply(dp, jnp.tanh(g.apply(p, z)[..., 0])).sum())(p), gp),
  }
  planned = layers.plan
  times = {}
  try:
    for _ in range(rounds):
      for name, rewrite in VARIANTS.items():
        layers.plan = lambda *a, rewrite=rewrite: rewrite(planned(*a))
        for k, (f, arg) in graphs.items():
          fn = jax.jit(lambda a, f=f: f(a))  # a new function: a new trace
          jax.block_until_ready(fn(arg))
          times.setdefault((k, name), []).append(common.timed(lambda: fn(arg), 7, 0).median)
  finally:
    layers.plan = planned
  return {k: 1e3 * statistics.median(v) for k, v in times.items()}


def main():
  p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  p.add_argument('--scales', default='study,paper')
  p.add_argument('--rounds', type=int, default=3)
  p.add_argument('--graphs', action='store_true')
  p.add_argument('--out', default=os.path.join(HERE, 'results', 'conv_forms_cpu.json'))
  a = p.parse_args()
  common.print_banner()
  results = {'rounds': a.rounds, 'layers': []}
  for scale in a.scales.split(','):
    b, ups, downs = SCALES[scale]
    print(f'== {scale} scale, batch {b}: ms per call, median of {a.rounds} rounds; '
          '* = the form layers.plan picks')
    for kind, shapes in (('up', ups), ('down', downs)):
      for (h, w, cin, cout) in shapes:
        base, cases = layer_cases(kind, b, h, w, cin, cout)
        med = time_layer(cases, a.rounds)
        cells = []
        for m in FORMS:
          picked = getattr(base, m)
          cells.append(f'{m.upper()}: ' + ' '.join(
              f"{form}{'*' if form == picked else ''} {1e3 * med[m, form]:.1f}"
              for form in FORMS[m] if (m, form) in med))
        print(f'  {kind:4s} {h:3d}x{w:<3d} {cin:3d}->{cout:<3d}  ' + ' | '.join(cells), flush=True)
        results['layers'].append({
            'scale': scale, 'kind': kind, 'batch': b, 'h': h, 'w': w, 'cin': cin, 'cout': cout,
            'plan': {m: getattr(base, m) for m in FORMS},
            'ms': {f'{m}/{form}': 1e3 * t for (m, form), t in med.items()}})
  if a.graphs:
    med = time_graphs(a.rounds)
    print(f'== gradients at the study scale: ms, median of {a.rounds} rounds '
          '(ratio to the plan)')
    for k in ('g_vjp', 'd_grad', 'r1', 'g_through_d'):
      print(f'  {k:12s} ' + '  '.join(
          f'{n} {med[k, n]:.1f} ({med[k, n] / med[k, "plan"]:.2f})' for n in VARIANTS))
    results['graphs'] = [{'gradient': k, 'variant': n, 'ms': t} for (k, n), t in med.items()]
  print('wrote', common.write_json(a.out, results))


if __name__ == '__main__':
  main()
