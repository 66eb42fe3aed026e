"""The speed/accuracy trade of GAN inversion: error against iterations.

    python benchmarks/invert_tradeoff.py [--workdir RUN] [--batch 8]

For each iteration count (50 ... 1000), inverts the same batch of target
scans and reports the reconstruction error (mean |x_tilde - x_target| in
normalised inverse depth over the target's valid pixels, and AbsRel in
metres) with seconds per scan (wall time / batch). Also the time per
iteration for one scan alone and per scan-iteration in a batch of 32.

With --workdir, targets are test scans of that run's dataset and the run's
EMA generator is inverted. Without it, a full-size (64x256, latent 512)
DUSty-I generator with random weights inverts its own samples, whose exact
latents exist: the error then measures how far the search gets in each
budget. Writes a table (JSON) and a plot (PNG) to benchmarks/results/, and
names the cheapest setting within 5% of the 1000-iteration error.
"""

import argparse
import os

import jax
import numpy as np

import common
from dusty_jax import codec, configs, inversion, sampling, trainer, writers
from dusty_jax.sensor import get_sensor

ITERS = (50, 100, 200, 500, 1000)


def random_generator():
  c = configs.default()
  sensor = get_sensor('kitti')
  setup = trainer.make_setup(c, sensor)
  state = trainer.init_state(setup, jax.random.key(0))
  return trainer.generator_params(setup, state.g_params, sensor.nominal_angles())


def errors(params, target, result):
  valid = np.asarray(target) > codec.ALPHA
  diff = np.abs(np.asarray(result['inv_depth']) - np.asarray(target))
  l1 = float(np.mean([d[v].mean() for d, v in zip(diff, valid)]))
  t, _ = codec.decode(target, params.sensor)
  p, _ = codec.decode(result['inv_depth'], params.sensor)
  t, p = np.asarray(t), np.asarray(p)
  absrel = float(np.mean([(np.abs(pp - tt)[v] / tt[v]).mean()
                          for pp, tt, v in zip(p, t, valid)]))
  return l1, absrel


def main():
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument('--workdir')
  ap.add_argument('--batch', type=int, default=8)
  ap.add_argument('--iters', default=','.join(map(str, ITERS)))
  ap.add_argument('--out', default=os.path.join(os.path.dirname(__file__), 'results'))
  a = ap.parse_args()
  info = common.print_banner()
  if a.workdir:
    import dusty_jax
    from dusty_jax.data import arrays, pipeline
    params, config = dusty_jax.load_checkpoint(a.workdir)
    d = pipeline.dataset_dir(config, params.sensor, log=print)
    test = arrays.load_split(d, 'test', params.sensor)[:a.batch]
    target = codec.encode(test, params.sensor)
    source = f'test scans of {a.workdir}'
  else:
    params = random_generator()
    target = sampling.sample(params, jax.random.key(42), a.batch)['scan']
    source = 'own samples of a random-weight full-size DUSty-I generator'
  print(f'{source}; batch {a.batch}')
  rows = []
  for n in map(int, a.iters.split(',')):
    # One timed run after one that compiles.
    t = common.timed(lambda: inversion.invert(params, target, num_steps=n), 1)
    dt, res = t.median, t.result
    l1, absrel = errors(params, target, res)
    rows.append(dict(iterations=n, l1=l1, abs_rel=absrel, s_per_scan=dt / a.batch,
                     ms_per_scan_iter=dt / a.batch / n * 1e3))
    print(f'  {n:5d} iters: L1 {l1:.4f}  AbsRel {absrel:.4f}  '
          f'{dt / a.batch:7.2f} s/scan  ({dt / a.batch / n * 1e3:.1f} ms/scan-iter)',
          flush=True)
  # Per-iteration speed: one scan alone, and a batch of 32.
  speed = {}
  for b in (1, 32):
    tgt = sampling.sample(params, jax.random.key(7), b)['scan']
    n = 50
    t = common.timed(lambda: inversion.invert(params, tgt, num_steps=n), 3)
    speed[b] = t.median / n * 1e3
    print(f'  batch {b:2d}: {speed[b]:.1f} ms per iteration '
          f'({speed[b] / b:.1f} ms per scan-iteration), median of 3 x {n} iters')
  ref = rows[-1]['l1']
  ok = [r for r in rows if r['l1'] <= 1.05 * ref]
  cheapest = min(ok, key=lambda r: r['iterations'])
  print(f'cheapest within 5% of the {rows[-1]["iterations"]}-iteration L1 error: '
        f'{cheapest["iterations"]} iterations ({cheapest["s_per_scan"]:.2f} s/scan)')
  common.write_json(os.path.join(a.out, 'invert_tradeoff.json'), dict(
      source=source, batch=a.batch, rows=rows, ms_per_iter_batch1=speed[1],
      ms_per_scan_iter_batch32=speed[32] / 32, cheapest_within_5pct=cheapest['iterations'],
      device=info['device_kind'], cpus=info['cpus']))
  its = [r['iterations'] for r in rows]
  writers.line_plot(os.path.join(a.out, 'invert_tradeoff.png'),
                    {'L1 error (inverse depth)': (its, [r['l1'] for r in rows])},
                    'iterations (log)', 'L1', logx=True,
                    title=f'{a.batch} scans; s/scan at 1000: {rows[-1]["s_per_scan"]:.1f}')


if __name__ == '__main__':
  main()
