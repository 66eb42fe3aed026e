"""Seconds per DUSty training step at the paper's size, per conv implementation.

    python benchmarks/train_step.py [--model dusty1] [--batch 32] [--repeats 7]
        [--impls matmul,xla] [--variants authors,fan_in_symmetric]

Prints seconds per step (median of --repeats, after a compile-and-warm-up
step) and images per second, for each convolution implementation and config
variant, for a step with the R1 penalty and one without; the lazy-R1 average
is for R1 every 16 steps. Variants: ``authors`` (the defaults: the authors'
eq-lr constants and DiffAugment distributions) and ``fan_in_symmetric``
(true fan-in constants, symmetric DiffAugment: the defaults before they
followed the authors). Results are also written to
benchmarks/results/train_step.json. Compare figures from one run only:
shared machines are noisy.
"""

import argparse
import os

import jax
import numpy as np

import common
from dusty_jax import configs, parallel, trainer
from dusty_jax.sensor import get_sensor


VARIANTS = {'authors': {},
            'fan_in_symmetric': {'eqlr': 'fan_in', 'augment_style': 'symmetric'}}
LAZY_EVERY = 16


def time_step(impl, r1, model, batch, repeats, sensor, variant='authors'):
  c = configs.default()
  c.update(VARIANTS[variant])
  c.model, c.impl, c.batch_size = model, impl, batch
  c.r1_every = 1
  c.r1_gamma = 1.0 if r1 else 0.0
  setup = trainer.make_setup(c, sensor)
  mesh = parallel.data_mesh()
  step = parallel.data_parallel(trainer.step_fn(setup), mesh)
  state = parallel.replicate(trainer.init_state(setup, jax.random.key(0)), mesh)
  x = np.random.default_rng(0).uniform(-1, 1, (batch,) + sensor.shape)
  x = parallel.shard_batch(x.astype(np.float32), mesh)
  key = jax.random.key(1)

  def run():
    nonlocal state
    state, _ = step(state, x, key)
    return state

  return common.timed(run, repeats)  # the warm-up step compiles


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--model', default='dusty1')
  p.add_argument('--sensor', default='kitti')
  p.add_argument('--batch', type=int, default=32)
  p.add_argument('--repeats', type=int, default=7)
  p.add_argument('--impls', default='matmul,xla')
  p.add_argument('--variants', default='authors')
  p.add_argument('--out', default=os.path.join(os.path.dirname(__file__), 'results',
                                               'train_step.json'))
  a = p.parse_args()
  sensor = get_sensor(a.sensor)
  r1_every = LAZY_EVERY
  info = common.print_banner()
  print(f'{a.model} {sensor.height}x{sensor.width} batch {a.batch}')
  rows = []
  for impl in a.impls.split(','):
    for variant in a.variants.split(','):
      res = {}
      for r1 in (True, False):
        t = time_step(impl, r1, a.model, a.batch, a.repeats, sensor, variant)
        med, times, compile_s = t.median, t.times, t.warmup[0]
        res[r1] = med
        rows.append(dict(impl=impl, variant=variant, r1=r1, median_s=med, times=times,
                         compile_s=compile_s, images_per_s=a.batch / med))
        print(f'  {impl:6s} {variant:16s} R1={"on " if r1 else "off"}: {med:6.2f} s/step '
              f'(min {min(times):.2f}, max {max(times):.2f}), '
              f'{a.batch / med:6.2f} img/s, compile {compile_s:.0f} s', flush=True)
      lazy = (res[True] + (r1_every - 1) * res[False]) / r1_every
      print(f'  {impl:6s} {variant:16s} lazy R1 every {r1_every}: {lazy:6.2f} s/step '
            f'average, {a.batch / lazy:6.2f} img/s')
  common.write_json(a.out, dict(model=a.model, shape=sensor.shape, batch=a.batch,
                                device=f'{info["device_count"]} x {info["device_kind"]}',
                                rows=rows))


if __name__ == '__main__':
  main()
