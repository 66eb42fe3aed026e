"""How far the authors' evaluation code (protocol 'paper') moves each metric.

    python benchmarks/protocols.py [--num 32] [--points 512] [--recon 8]

On the default simulated HDL-64E data (cached by the first training run):
the "real" set is the first --num test scans, the "generated" set the first
--num training scans (other scenes of the same simulator, standing in for a
generator that matches the data). Each of the authors' differences is
measured alone against the reference protocol, then all together:
  * FPS: how many clouds hold the origin (pixel 0 dropped) and the valid
    points nearer than 3.79 m, and the point metrics on their clouds;
  * JSD: the eps bias, on identical sets and on real vs generated;
  * SWD: each of direction scaling, shifted pyramid and shared patch
    positions alone, and all three (over --seeds);
  * the test subset: which scans [skip:limit:skip] takes against linspace;
  * Table III's Chamfer distance: "reconstructions" are the simulator's
    complete depth with drops drawn afresh from its true drop probability
    (what a perfect DUSty would render), scored as the invert CLI scores.
Prints the figures and writes benchmarks/results/protocols.json.
"""

import argparse
import os

import jax
import numpy as np

import common
from dusty_jax import codec, configs
from dusty_jax.data import arrays, pipeline
from dusty_jax.metrics import chamfer, clouds, point_sets, protocol, swd
from dusty_jax.sensor import from_config

POINT_METRICS = ('jsd', 'cov', 'mmd', '1nna')


def point_metrics(ref, gen, jsd_protocol='reference'):
  """JSD, COV, MMD, 1-NNA of two sets of sampled clouds."""
  d_rs = chamfer.pairwise(ref, gen)
  mmd, cov = point_sets.mmd_cov(d_rs.T)
  return {'jsd': point_sets.jsd(ref, gen, protocol=jsd_protocol), 'cov': cov, 'mmd': mmd,
          '1nna': point_sets.one_nna(chamfer.pairwise(ref), d_rs, chamfer.pairwise(gen))}


def relative(a, b):
  return {k: (b[k] - a[k]) / abs(a[k]) if a[k] else None for k in a}


def show(label, m):
  print(f'  {label:38s}' + '  '.join(f'{k} {v:.5g}' for k, v in m.items()))


def main():
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument('--num', type=int, default=32)
  ap.add_argument('--points', type=int, default=512)
  ap.add_argument('--seeds', type=int, default=3, help='SWD seeds')
  ap.add_argument('--recon', type=int, default=8, help='scans for Table III')
  ap.add_argument('--out', default=os.path.join(os.path.dirname(__file__), 'results',
                                                'protocols.json'))
  a = ap.parse_args()
  common.print_banner()
  config = configs.default()  # the data of experiments/synthetic.py
  config.sensor.preset = 'kitti'
  config.data.num_synthetic = 2000
  sensor = from_config(config.sensor)
  d = pipeline.dataset_dir(config, sensor, log=print)
  angles = arrays.load_angles(d, sensor)
  test = arrays.load_split(d, 'test', sensor)
  n, p = a.num, a.points
  real_depth, fake_depth = np.asarray(test[:n]), np.asarray(arrays.load_split(
      d, 'train', sensor)[:n])
  real = np.asarray(codec.encode(real_depth, sensor))
  fake = np.asarray(codec.encode(fake_depth, sensor))
  print(f'{n} clouds a set, {p} points, data {d}')
  out = dict(num=n, points=p, data=d)

  # --- FPS -------------------------------------------------------------------
  valid = np.asarray(codec.valid_depth(real_depth, sensor))
  near_m = np.sqrt(clouds.PAPER_MIN_SQUARED_NORM) * sensor.max_depth
  stats = dict(pixel0_dropped=float(np.mean(~valid[:, 0, 0])),
               valid_nearer_than_m=near_m,
               valid_near_share=float(((real_depth < near_m) & valid).sum() / valid.sum()))
  sets = {}
  t = {}
  for proto in ('reference', 'paper'):
    sets[proto] = [protocol.prepare_set(real, angles, sensor, p, protocol=proto)[0]]
    dt, prepared = common.seconds(  # the second set: compiled already
        lambda: protocol.prepare_set(fake, angles, sensor, p, protocol=proto))
    sets[proto].append(prepared[0])
    t[proto] = dt / n * 1e3
  paper_real = sets['paper'][0]
  stats['paper_clouds_with_origin'] = float(np.mean((paper_real == 0).all(-1).any(-1)))
  stats['paper_points_nearer'] = float(np.mean(
      np.linalg.norm(paper_real, axis=-1)[:, 1:] * sensor.max_depth < near_m))
  stats['reference_points_nearer'] = float(np.mean(
      np.linalg.norm(sets['reference'][0], axis=-1) * sensor.max_depth < near_m))
  stats['fps_ms_per_cloud'] = t
  m_ref = point_metrics(*sets['reference'])
  m_fps = point_metrics(*sets['paper'])
  stats.update(metrics_reference=m_ref, metrics_paper_fps=m_fps,
               relative=relative(m_ref, m_fps))
  out['fps'] = stats
  print('FPS (paper: pixel 0 first, nothing within '
        f'{near_m:.2f} m): pixel 0 dropped in {stats["pixel0_dropped"]:.0%} of scans, '
        f'{stats["valid_near_share"]:.1%} of valid points that near')
  print(f'  paper clouds holding the origin: {stats["paper_clouds_with_origin"]:.0%}; '
        f'FPS {t["reference"]:.1f} / {t["paper"]:.1f} ms per cloud (reference / paper)')
  show('reference clouds', m_ref)
  show('paper clouds', m_fps)

  # --- JSD -------------------------------------------------------------------
  ref_r, ref_f = sets['reference']
  jsd = dict(identical_reference=point_sets.jsd(ref_r, ref_r),
             identical_paper=point_sets.jsd(ref_r, ref_r, protocol='paper'),
             real_fake_reference=m_ref['jsd'],
             real_fake_eps_only=point_sets.jsd(ref_r, ref_f, protocol='paper'),
             real_fake_paper=point_sets.jsd(*sets['paper'], protocol='paper'))
  out['jsd'] = jsd
  print('JSD (eps bias): identical sets {identical_reference:.5f} -> {identical_paper:.5f};'
        ' real vs generated {real_fake_reference:.5f} -> {real_fake_eps_only:.5f} (eps only)'
        ' -> {real_fake_paper:.5f} (with paper FPS)'.format(**jsd))

  # --- SWD -------------------------------------------------------------------
  variants = {'reference': dict(protocol='reference'),
              **{f'{part} only': dict(protocol='paper', paper_parts=(part,))
                 for part in swd.PAPER_PARTS},
              'paper (all)': dict(protocol='paper')}
  swds = {k: [swd.swd(jax.random.key(s), real, fake, **kw)['swd_mean']
              for s in range(a.seeds)] for k, kw in variants.items()}
  out['swd'] = {k: dict(values=v, ratio=[x / r for x, r in zip(v, swds['reference'])])
                for k, v in swds.items()}
  print(f'SWD over {a.seeds} seeds (value, x reference):')
  for k, v in out['swd'].items():
    print(f'  {k:38s}{np.mean(v["values"]):.5f}  x{min(v["ratio"]):.2f}..'
          f'{max(v["ratio"]):.2f}')

  # --- end to end ------------------------------------------------------------
  e2e = {}
  for proto in ('reference', 'paper'):
    e2e[f'{proto}_seconds'], e2e[proto] = common.seconds(lambda: protocol.compare(
        real, fake, angles, sensor=sensor, protocol=proto, num_points=p, seed=0))
    e2e[f'{proto}_identical'] = protocol.compare(real, real, angles, sensor=sensor,
                                                 protocol=proto, num_points=p, seed=0)
  e2e['relative'] = relative(e2e['reference'], e2e['paper'])
  out['end_to_end'] = e2e
  print('all together, compare():')
  for k in ('reference', 'paper', 'reference_identical', 'paper_identical'):
    show(k + (f' ({e2e[k + "_seconds"]:.1f} s)' if k + '_seconds' in e2e else ''), e2e[k])

  # --- test subset -------------------------------------------------------------
  ev, pa = protocol.subset(len(test), n), protocol.subset(len(test), n, 'paper')
  sub = dict(split=len(test), linspace=ev.tolist(), paper=pa.tolist(),
             shared=len(set(ev.tolist()) & set(pa.tolist())))
  sub_real = np.asarray(codec.encode(np.asarray(test[pa][:len(fake)]), sensor))
  m_sub = protocol.compare(sub_real, fake[:len(sub_real)], angles, sensor=sensor,
                           num_points=p, seed=0)
  m_lin = protocol.compare(np.asarray(codec.encode(np.asarray(test[ev]), sensor)),
                           fake[:len(ev)], angles, sensor=sensor, num_points=p, seed=0)
  sub.update(metrics_linspace=m_lin, metrics_paper_subset=m_sub)
  out['subset'] = sub
  print(f'test subset of {n} from {len(test)}: linspace {ev[:4].tolist()}...{ev[-1]}, '
        f'paper {pa[:4].tolist()}...{pa[-1]} ({len(pa)} scans), {sub["shared"]} shared')
  show('linspace subset (reference metrics)', m_lin)
  show('paper subset (reference metrics)', m_sub)

  # --- Table III Chamfer -------------------------------------------------------
  from dusty_jax.metrics import reconstruction
  r = a.recon
  target = real_depth[:r]
  complete = np.asarray(arrays.load_split(d, 'test', sensor, 'complete')[:r])
  drop = np.asarray(arrays.load_split(d, 'test', sensor, 'drop_prob')[:r])
  rng = np.random.default_rng(0)
  rec = np.where(rng.uniform(size=drop.shape) >= drop, complete, 0.0).astype(np.float32)
  dep, val = codec.decode(codec.encode(rec, sensor), sensor)
  result = {'inv_depth': np.asarray(codec.encode(complete, sensor)),
            'valid': np.asarray(val), 'points': np.asarray(codec.to_points(dep, angles))}
  cd = {}
  for proto in ('reference', 'paper'):
    dt, errs = common.seconds(
        lambda: reconstruction.errors(target, result, angles, sensor, proto))
    cd[proto] = errs['cd'].tolist()
    cd[f'{proto}_seconds_per_scan'] = dt / r
  cd['ratio'] = [b / a_ for a_, b in zip(cd['reference'], cd['paper'])]
  cd['valid_fraction'] = valid[:r].mean(axis=(1, 2)).tolist()
  out['reconstruction_cd'] = cd
  print(f'Table III Chamfer over {r} scans (x1e4): reference '
        f'{np.mean(cd["reference"]) * 1e4:.3f}, paper {np.mean(cd["paper"]) * 1e4:.3f} '
        f'(ratio {min(cd["ratio"]):.2f}..{max(cd["ratio"]):.2f}; valid fraction '
        f'{np.mean(cd["valid_fraction"]):.2f}); {cd["reference_seconds_per_scan"]:.2f} / '
        f'{cd["paper_seconds_per_scan"]:.2f} s per scan')

  print(f'saved {common.write_json(a.out, out)}')


if __name__ == '__main__':
  main()
