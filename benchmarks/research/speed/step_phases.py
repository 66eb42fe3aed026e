"""Where a training step's time goes, phase by phase.

    python benchmarks/research/speed/step_phases.py [--scale study|paper] [--impls matmul,xla]

Each phase is jit-compiled alone and timed (median of --repeats after a
compile-and-warm-up call), on the shapes of the chosen scale (study: the CPU
study's DUSty-I, latent 128, channels 16..128, batch 16; paper: latent 512,
channels 64..512, batch 32):

  * g_forward: generator + Gumbel composition of a batch;
  * g_backward: the same with its VJP pulled back (what the G update costs
    besides D);
  * augment: DiffAugment of a batch, per-example keys;
  * d_forward, d_grad: D on a batch; D's loss gradient on real + fake;
  * r1: the R1 penalty's gradient with respect to D's parameters (a double
    backward through D);
  * d_step, g_step, ema: trainer's pure pieces as the step calls them;
  * step: the whole train_step on one device (jit(shard_map)), and the
    loop's wall time per step including the host's work between steps.

Prints the table and writes benchmarks/research/speed/results/step_phases.json.
"""

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

# benchmarks/ holds common.py, shared with the product benchmarks.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..'))
import common
from dusty_jax import augment, configs, losses, parallel, trainer
from dusty_jax.sensor import get_sensor

SCALES = {'paper': dict(latent_dim=512, ch_base=64, ch_max=512, batch_size=32),
          'study': dict(latent_dim=128, ch_base=16, ch_max=128, batch_size=16)}
HERE = os.path.dirname(os.path.abspath(__file__))


def phases(c, sensor, repeats):
  setup = trainer.make_setup(c, sensor)
  state = trainer.init_state(setup, jax.random.key(0))
  b = c.batch_size
  rng = np.random.default_rng(0)
  real = jnp.asarray(rng.uniform(-1, 1, (b,) + sensor.shape), jnp.float32)
  z = jax.random.normal(jax.random.key(1), (b, c.latent_dim))
  keys = jax.random.split(jax.random.key(2), b)
  aug_keys = (keys, jax.random.split(jax.random.key(3), b))
  d = setup.discriminator
  gp, dp = state.g_params, state.d_params

  def fakes(p):
    return trainer.fake_scans(setup, p, z, keys)['scan']

  def g_backward(p):
    out, vjp = jax.vjp(fakes, p)
    return vjp(jnp.ones_like(out))

  def d_grad(p):
    return jax.grad(lambda p: losses.d_loss(d.apply(p, real), d.apply(p, real[::-1])))(p)

  def r1(p):
    return jax.grad(lambda p: losses.r1_penalty(lambda x: d.apply(p, x), real))(p)

  fake = fakes(gp)
  fake_out, fake_vjp = jax.vjp(fakes, gp)

  def d_step(dp, opt):
    return trainer.d_step(setup, dp, opt, real, fake, aug_keys, True)

  def g_step(gp, opt):
    return trainer.g_step(setup, gp, opt, dp, fake_out, fake_vjp, keys)

  pieces = {
      'g_forward': (fakes, (gp,)),
      'g_backward': (g_backward, (gp,)),
      'augment': (lambda x: augment.per_example(keys, x, setup.policy,
                                                setup.augment_style), (real,)),
      'd_forward': (lambda p: d.apply(p, real), (dp,)),
      'd_grad': (d_grad, (dp,)),
      'r1': (r1, (dp,)),
      'd_step': (d_step, (dp, state.d_opt)),
      'g_step': (g_step, (gp, state.g_opt)),
      'ema': (lambda e, p: trainer.ema_update(e, p, 0.99), (state.ema_params, gp)),
  }
  out = {}
  for name, (fn, args) in pieces.items():
    f = jax.jit(fn)
    out[name] = common.timed(lambda: f(*args), repeats).median
  mesh = parallel.data_mesh(jax.devices()[:1])
  step = parallel.data_parallel(trainer.step_fn(setup), mesh)
  st = parallel.replicate(state, mesh)
  batch = parallel.shard_batch(np.asarray(real), mesh)
  key = jax.random.key(4)

  def run():
    nonlocal st
    st, m = step(st, batch, key)
    return st

  out['step'] = common.timed(run, repeats).median
  # The loop as train_and_evaluate runs it: host batches put on the device.
  host = np.asarray(real)
  t = time.perf_counter()
  for _ in range(repeats):
    st, m = step(st, parallel.shard_batch(host, mesh), key)
  jax.block_until_ready(st)
  out['loop_per_step'] = (time.perf_counter() - t) / repeats
  return out


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--scale', default='study', choices=sorted(SCALES))
  p.add_argument('--impls', default='matmul,xla')
  p.add_argument('--repeats', type=int, default=7)
  p.add_argument('--out', default=os.path.join(HERE, 'results', 'step_phases.json'))
  a = p.parse_args()
  common.print_banner()
  sensor = get_sensor('kitti')
  rows = {}
  for impl in a.impls.split(','):
    c = configs.default()
    c.update(SCALES[a.scale])
    c.impl = impl
    rows[impl] = phases(c, sensor, a.repeats)
  impls = list(rows)
  print(f'{a.scale} scale, DUSty-I, batch {SCALES[a.scale]["batch_size"]}: ms (median)')
  print(f'{"phase":16s}' + ''.join(f'{i:>10s}' for i in impls))
  for name in rows[impls[0]]:
    print(f'{name:16s}' + ''.join(f'{1e3 * rows[i][name]:10.1f}' for i in impls))
  common.write_json(a.out, dict(scale=a.scale, batch=SCALES[a.scale]['batch_size'],
                                seconds=rows))


if __name__ == '__main__':
  main()
