"""Seconds per DUSty training step and per inversion, beside the authors' code.

    python benchmarks/train_step.py [--scales study,paper] [--impls matmul]
        [--variants authors] [--invert 1,32] [--authors-dir PATH [--authors-amp]]
        [--rounds N] [--cpu-devices N]

For each scale (``paper``: latent 512, channels 64..512, batch 32; ``study``:
the CPU study's latent 128, channels 16..128, batch 16; both 64x256), each
conv implementation and config variant: seconds per train step with R1
every step and without (median of --repeats after a compile-and-warm-up
step), XLA's FLOP count of the compiled step, and the fraction of the
machine's float32 matmul peak (measured in the same run) that it reaches.
With ``--invert``, the time of 100-iteration inversions of batches of these
sizes with the paper-size generator. Variants: ``authors`` (the defaults)
and ``fan_in_symmetric`` (the defaults before they followed the authors).

With ``--authors-dir`` (a checkout of kazuto1011/dusty-gan, never part of
this repository, and torch installed), the authors' step and inversion run
right after ours in the same run (benchmarks/authors_step.py, in a
subprocess), and the ratios ours / theirs are printed; ``--rounds N`` times
ours then theirs N times per scale and prints each round's ratio and the
median of them, which cancels the machine's drift between rounds. On a CPU
the step runs on the devices the trainer gives it (parallel.use_cpu_cores:
up to two per core, shards of 4 or more) unless ``--cpu-devices`` or
XLA_FLAGS' device count says otherwise; inversion runs on one. Results go to
benchmarks/results/train_step.json (``--out``). Compare figures from one
run only: shared machines are noisy.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

import jax
import jax.numpy as jnp
import numpy as np

import common
from dusty_jax import configs, inversion, parallel, sampling, trainer
from dusty_jax.sensor import get_sensor


VARIANTS = {'authors': {},
            'fan_in_symmetric': {'eqlr': 'fan_in', 'augment_style': 'symmetric'}}
SCALES = {  # latent, ch_base, ch_max, batch (benchmarks/authors_step.py: the same).
    'paper': dict(latent_dim=512, ch_base=64, ch_max=512, batch_size=32),
    'study': dict(latent_dim=128, ch_base=16, ch_max=128, batch_size=16),
}
LAZY_EVERY = 16
INVERT_ITERS = 100
HERE = os.path.dirname(os.path.abspath(__file__))


def make_config(scale, impl, r1, model='dusty1', variant='authors', batch=None):
  c = configs.default()
  c.update(VARIANTS[variant])
  c.update(SCALES[scale])
  c.model, c.impl = model, impl
  if batch:
    c.batch_size = batch
  c.r1_every = 1
  c.r1_gamma = 1.0 if r1 else 0.0
  return c


def time_step(c, sensor, repeats):
  """(Timing, flops) of the data-parallel train step under config ``c``."""
  setup = trainer.make_setup(c, sensor)
  mesh = parallel.data_mesh()
  step = parallel.data_parallel(trainer.step_fn(setup), mesh)
  state = parallel.replicate(trainer.init_state(setup, jax.random.key(0)), mesh)
  x = np.random.default_rng(0).uniform(-1, 1, (c.batch_size,) + sensor.shape)
  x = parallel.shard_batch(x.astype(np.float32), mesh)
  key = jax.random.key(1)
  flops = float('nan')
  try:
    cost = step.lower(state, x, key).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    flops = float(cost.get('flops', float('nan'))) * mesh.size  # XLA counts per device
  except Exception as e:  # cost analysis is best effort on some backends.
    print(f'  (no XLA cost analysis: {e})')

  def run():
    nonlocal state
    state, _ = step(state, x, key)
    return state

  return common.timed(run, repeats), flops  # the warm-up step compiles


def matmul_peak(repeats=5) -> float:
  """Float32 FLOP/s of a large matmul on the default device."""
  n = 4096 if jax.default_backend() != 'cpu' else 1024
  a = jax.random.normal(jax.random.key(0), (n, n), jnp.float32)
  f = jax.jit(lambda a: a @ a)
  t = common.timed(lambda: f(a), repeats)
  return 2 * n ** 3 / t.median


def iteration_flops(params, tgt):
  """FLOPs of one search iteration's gradient for the batch ``tgt`` (XLA's
  cost analysis of the objective's per-scan gradient, as invert computes it)."""
  apply = params.module(None).apply
  f = jax.jit(jax.vmap(jax.grad(
      lambda z, t, m: inversion.scan_loss(params, apply, z, t, m))))
  z = jnp.zeros((len(tgt), params.latent_dim), jnp.float32)
  cost = f.lower(z, tgt, inversion.target_mask(tgt)).compile().cost_analysis()
  return (cost[0] if isinstance(cost, list) else cost)['flops']


def time_inversion(batches, repeats, peak):
  """Seconds of an INVERT_ITERS-iteration inversion, paper-size DUSty-I, and
  its FLOPs (``{batch: seconds}``, ``{batch: FLOPs}``)."""
  c = make_config('paper', '', True)
  sensor = get_sensor('kitti')
  setup = trainer.make_setup(c, sensor)
  state = trainer.init_state(setup, jax.random.key(0))
  params = trainer.generator_params(setup, state.g_params, sensor.nominal_angles())
  out, flops = {}, {}
  for b in batches:
    tgt = sampling.sample(params, jax.random.key(7), b)['scan']
    t = common.timed(lambda: inversion.invert(params, tgt, num_steps=INVERT_ITERS), repeats)
    out[b], flops[b] = t.median, INVERT_ITERS * iteration_flops(params, tgt)
    print(f'  ours: inversion, {INVERT_ITERS} iterations, batch {b}: {t.median:.3f} s '
          f'({1e3 * t.median / INVERT_ITERS / b:.2f} ms per scan-iteration), '
          f'{flops[b] / 1e9:.1f} GFLOP, {flops[b] / t.median / peak:.1%} of peak', flush=True)
  return out, flops


def run_authors(a, scale, invert):
  """The authors' step (and inversion) in a subprocess; their JSON."""
  with tempfile.TemporaryDirectory() as d:
    out = os.path.join(d, 'authors.json')
    cmd = [a.authors_python, os.path.join(HERE, 'authors_step.py'), '--authors-dir',
           a.authors_dir, '--device', a.authors_device, '--scale', scale, '--batch',
           str(SCALES[scale]['batch_size']), '--repeats', str(a.repeats),
           '--invert', invert, '--invert-iters', str(INVERT_ITERS), '--out', out]
    if a.authors_amp:
      cmd.append('--amp')
    if a.authors_threads:
      cmd += ['--threads', str(a.authors_threads)]
    subprocess.run(cmd, check=True)
    with open(out) as f:
      return json.load(f)


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--model', default='dusty1')
  p.add_argument('--scales', default='paper')
  p.add_argument('--repeats', type=int, default=5)
  p.add_argument('--impls', default='', help="'' = the backend's default; or matmul,xla")
  p.add_argument('--variants', default='authors')
  p.add_argument('--invert', default='', help='inversion batch sizes, e.g. 1,32')
  p.add_argument('--rounds', type=int, default=1,
                 help='times ours then theirs, per scale; the ratio is per round')
  p.add_argument('--authors-dir', default='')
  p.add_argument('--authors-python', default=sys.executable)
  p.add_argument('--authors-device', default='',
                 help="cuda or cpu; default: cuda where JAX's backend is a GPU")
  p.add_argument('--authors-amp', action='store_true',
                 help="their mixed precision (their config's default on a GPU)")
  p.add_argument('--authors-threads', type=int, default=0)
  p.add_argument('--cpu-devices', type=int, default=0,
                 help="CPU devices; 0: the library's choice (parallel.use_cpu_cores)")
  p.add_argument('--out', default=os.path.join(HERE, 'results', 'train_step.json'))
  a = p.parse_args()
  if a.cpu_devices:  # before JAX's first operation, as the trainer does.
    jax.config.update('jax_num_cpu_devices', a.cpu_devices)
  else:
    parallel.use_cpu_cores(min(SCALES[s]['batch_size'] for s in a.scales.split(',')))
  a.authors_device = a.authors_device or ('cuda' if jax.default_backend() == 'gpu' else 'cpu')
  sensor = get_sensor('kitti')
  info = common.print_banner()
  peak = matmul_peak()
  print(f'float32 matmul peak measured now: {peak / 1e9:.1f} GFLOP/s', flush=True)
  rows, authors, ratios = [], {}, []
  for scale in a.scales.split(','):
    batch = SCALES[scale]['batch_size']
    ours_r, theirs_r = [], []
    for rnd in range(a.rounds):
      print(f'== {a.model} {scale} scale, {sensor.height}x{sensor.width}, batch {batch}'
            + (f', round {rnd + 1} of {a.rounds}' if a.rounds > 1 else ''), flush=True)
      for impl in a.impls.split(','):
        for variant in a.variants.split(','):
          res = {}
          for r1 in (True, False):
            t, flops = time_step(make_config(scale, impl, r1, a.model, variant), sensor,
                                 a.repeats)
            res[r1] = t.median
            rows.append(dict(scale=scale, round=rnd, impl=impl or 'default', variant=variant,
                             r1=r1, batch=batch, median_s=t.median, times=t.times,
                             compile_s=t.warmup[0], images_per_s=batch / t.median,
                             flops=flops, peak_fraction=flops / t.median / peak))
            print(f'  ours {impl or "default":7s} {variant:16s} R1={"on " if r1 else "off"}: '
                  f'{t.median:7.4f} s/step (min {min(t.times):.4f}), '
                  f'{batch / t.median:7.1f} img/s, {flops / 1e9:.1f} GFLOP, '
                  f'{100 * flops / t.median / peak:.1f}% of peak, compile {t.warmup[0]:.0f} s',
                  flush=True)
          lazy = (res[True] + (LAZY_EVERY - 1) * res[False]) / LAZY_EVERY
          print(f'  ours {impl or "default":7s} {variant:16s} lazy R1 every {LAZY_EVERY}: '
                f'{lazy:7.4f} s/step average')
      if a.authors_dir:
        last = rnd == a.rounds - 1
        theirs = run_authors(a, scale, a.invert if scale == 'paper' and last else '')
        authors.setdefault(scale, {}).update(theirs)
        ours_r.append(min(r['median_s'] for r in rows if r['scale'] == scale and r['r1']
                          and r['variant'] == 'authors' and r['round'] == rnd))
        theirs_r.append(theirs['train_step_s'])
        if a.rounds > 1:
          print(f'  round {rnd + 1}: ours {ours_r[-1]:.4f} s, theirs {theirs_r[-1]:.4f} s, '
                f'ours / theirs {ours_r[-1] / theirs_r[-1]:.3f}', flush=True)
    if a.authors_dir:
      ratios.append(dict(what=f'train step, {scale} scale, R1 every step',
                         ours=statistics.median(ours_r), theirs=statistics.median(theirs_r),
                         rounds=[dict(ours=o, theirs=t, ratio=o / t)
                                 for o, t in zip(ours_r, theirs_r)],
                         median_round_ratio=statistics.median(
                             o / t for o, t in zip(ours_r, theirs_r))))
  inv, inv_flops = time_inversion([int(b) for b in a.invert.split(',') if b], a.repeats,
                                  peak) if a.invert else ({}, {})
  for b, t in inv.items():
    if 'paper' in authors and f'invert_{b}_s' in authors['paper']:
      ratios.append(dict(what=f'inversion, batch {b}, {INVERT_ITERS} iterations',
                         ours=t, theirs=authors['paper'][f'invert_{b}_s']))
  for r in ratios:
    r['ours_over_theirs'] = r['ours'] / r['theirs']
    print(f'{r["what"]}: ours {r["ours"]:.4f} s, theirs {r["theirs"]:.4f} s: ours / theirs '
          f'{r["ours_over_theirs"]:.3f} (speed-up x{1 / r["ours_over_theirs"]:.2f})'
          + (f'; median of the per-round ratios {r["median_round_ratio"]:.3f}'
             if len(r.get('rounds', [])) > 1 else ''))
  common.write_json(a.out, dict(model=a.model, shape=sensor.shape,
                                device=f'{info["device_count"]} x {info["device_kind"]}',
                                matmul_peak_flops=peak, rows=rows,
                                inversion_s={str(b): t for b, t in inv.items()},
                                inversion_flops={str(b): f for b, f in inv_flops.items()},
                                authors=authors, ratios=ratios))


if __name__ == '__main__':
  main()
