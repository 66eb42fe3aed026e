"""Other sensors: reading and unfolding speed per format, the real samples.

    python benchmarks/sensors.py [--points 100000] [--repeats 15]

Part 1, speed: reading and unfolding one sweep of ~100k points in each
format, on one core.

A simulated sweep (float32 x, y, z, intensity; uint16 ring; uint8
return_type; float64 time_stamp: a driver's fields; one return in each of
--points firings of the OS1-128 preset, 128 x 1024) is written once
per format with data.write_points, then read with data.read_points: the
first read (an Ouster recording's builds the SDK's XYZ table, kept for the
next) and the median of ``--repeats`` more, in this one process pinned to
one CPU. The Ouster sample recording (../shared, 128 x 1024
pixels, ~107k returns; needs ouster-sdk) is read as it is, where present.
Each read sweep is then unfolded into the OS1-128 preset's 128 x 1024 image
(the Ouster recording into its own calibration's 128 x 1024) with its ring
field and without (rows by elevation): median of ``--repeats``. The
target: reading and unfolding 100k points under 50 ms on one core. Prints a
table.

Part 2, the real samples in ../shared/data/sensors-sample (a VLP-16, a
Hesai PandarXT16, an Ouster OS1-128 with its metadata; skipped where
absent): each sweep's rows from its ring field against rows from the
nearest beam's elevation (share of points that agree, share of pixels
equal), and a spec estimated from the points with and without the ring
field against the published table (VLP-16 manual; Hesai's XT16 manual: 16
beams from +15 to -15 degrees, 2 apart) or the unit's metadata (Ouster):
mean absolute elevation error, beams found, seconds. The picture of the
three sweeps as range images: benchmarks/results/sensors_real.png.

Writes benchmarks/results/sensors.json (``--out``).
"""

import argparse
import dataclasses
import os
import statistics
import tempfile
import time

import numpy as np

import common
from dusty_jax import sensor as sensor_lib
from dusty_jax.data import estimate, read_points, ring_field, unfolding, write_points
from dusty_jax.errors import UserError

HERE = os.path.dirname(os.path.abspath(__file__))
SAMPLES = os.path.join(HERE, '..', '..', 'shared', 'data', 'sensors-sample')
OUSTER_PCAP = os.path.join(SAMPLES, 'OS-1-128_v2.3.0_1024x10_lb_n3.pcap')
OUSTER_JSON = OUSTER_PCAP.replace('_lb_n3.pcap', '.json')

# (label, file name, encoding) of each format timed.
FORMATS = [
    ('KITTI .bin', 'sweep.bin', None),
    ('nuScenes .pcd.bin', 'sweep.pcd.bin', None),
    ('PCD binary', 'binary.pcd', 'binary'),
    ('PCD binary_compressed', 'compressed.pcd', 'binary_compressed'),
    ('PCD ascii', 'ascii.pcd', 'ascii'),
    ('PLY binary', 'binary.ply', 'binary'),
    ('PLY ascii', 'ascii.ply', 'ascii'),
    ('.npy structured', 'structured.npy', None),
]


SWEEP_SENSOR = sensor_lib.PRESETS['os1-128']  # 128 x 1024 firings: room for 100k returns


def sweep(n: int, seed: int = 0) -> dict:
  """A sweep of n returns of SWEEP_SENSOR at 1-80 m, each in its own
  (ring, firing), with a driver's fields: what unfold takes for a sweep of
  that sensor (a random cloud is refused as no sweep of it)."""
  rng = np.random.default_rng(seed)
  spec = SWEEP_SENSOR
  if n > spec.height * spec.native_width:
    raise SystemExit(f'--points {n}: at most {spec.height * spec.native_width} '
                     f'(one return per firing of {spec.name})')
  cell = rng.choice(spec.height * spec.native_width, n, replace=False)
  ring = (cell // spec.native_width).astype(np.uint16)
  elevation = spec.elevation[ring]
  azimuth = np.pi * (1 - 2 * (cell % spec.native_width + 0.5) / spec.native_width)
  r = rng.uniform(1, 80, n)
  return {
      'x': (r * np.cos(elevation) * np.cos(azimuth)).astype(np.float32),
      'y': (r * np.cos(elevation) * np.sin(azimuth)).astype(np.float32),
      'z': (r * np.sin(elevation)).astype(np.float32),
      'intensity': rng.uniform(0, 255, n).astype(np.float32),
      'ring': ring,
      'return_type': rng.integers(0, 3, n).astype(np.uint8),
      'time_stamp': 1.67e9 + rng.uniform(0, 0.1, n),
  }


def _median_ms(fn, repeats: int) -> float:
  times = []
  for _ in range(repeats):
    t = time.perf_counter()
    fn()
    times.append(1e3 * (time.perf_counter() - t))
  return statistics.median(times)


def time_reads(path: str, repeats: int, sensor) -> dict:
  """The first read (ms), then median, min and max of ``repeats`` more; points
  read; the median unfolding with and without the ring field."""
  t = time.perf_counter()
  fields = read_points(path)
  first = 1e3 * (time.perf_counter() - t)
  times = []
  for _ in range(repeats):
    t = time.perf_counter()
    read_points(path)
    times.append(1e3 * (time.perf_counter() - t))
  ring = ring_field(fields)
  unfold_ring = _median_ms(lambda: unfolding.unfold(fields, sensor, ring=ring), repeats)
  unfold_bare = _median_ms(lambda: unfolding.unfold(fields, sensor), repeats)
  return {'first_ms': first, 'median_ms': statistics.median(times), 'min_ms': min(times), 'max_ms': max(times),
          'points': int(len(fields['x'])), 'bytes': os.path.getsize(path),
          'unfold_ring_ms': unfold_ring, 'unfold_no_ring_ms': unfold_bare,
          'read_and_unfold_ms': statistics.median(times) + max(unfold_ring, unfold_bare)}


def main():
  ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  ap.add_argument('--points', type=int, default=100_000)
  ap.add_argument('--repeats', type=int, default=15)
  ap.add_argument('--out', default=os.path.join(HERE, 'results', 'sensors.json'))
  ap.add_argument('--picture', default=os.path.join(HERE, 'results', 'sensors_real.png'))
  args = ap.parse_args()
  if hasattr(os, 'sched_setaffinity'):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})  # one core
  load = os.getloadavg()
  print(f'load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; one core; '
        f'{args.points} points; median of {args.repeats} reads', flush=True)
  fields = sweep(args.points)
  results = {}
  with tempfile.TemporaryDirectory() as d:
    for label, name, encoding in FORMATS:
      path = os.path.join(d, name)
      try:
        write_points(path, fields, encoding=encoding)
      except UserError as e:  # an optional reader missing
        print(f'{label:24s} skipped: {e}')
        continue
      results[label] = time_reads(path, args.repeats, SWEEP_SENSOR)
  if os.path.exists(OUSTER_PCAP):
    try:
      results['Ouster .pcap (sample)'] = time_reads(
          OUSTER_PCAP, args.repeats, sensor_lib.from_ouster_metadata(OUSTER_JSON))
    except UserError as e:
      print(f'{"Ouster .pcap (sample)":24s} skipped: {e}')
  print(f'{"format":24s} {"points":>8s} {"MB":>6s} {"first ms":>9s} {"read ms":>8s} '
        f'{"min":>7s} {"max":>7s} {"unfold ring":>12s} {"no ring":>8s} {"read+unfold":>12s}')
  for label, r in results.items():
    print(f'{label:24s} {r["points"]:8d} {r["bytes"] / 1e6:6.2f} {r["first_ms"]:9.2f} '
          f'{r["median_ms"]:8.2f} {r["min_ms"]:7.2f} {r["max_ms"]:7.2f} '
          f'{r["unfold_ring_ms"]:12.2f} {r["unfold_no_ring_ms"]:8.2f} '
          f'{r["read_and_unfold_ms"]:12.2f}')
  real = real_samples(args.picture)
  common.write_json(args.out, {'points': args.points, 'repeats': args.repeats,
                               'load_average': load, 'formats': results, 'real': real,
                               'command': f'python benchmarks/sensors.py --points '
                                          f'{args.points} --repeats {args.repeats}'})
  print('wrote', args.out)


def real_samples(picture: str) -> dict:
  """Part 2 (module docstring): rows, estimates and the picture."""
  published = sensor_lib.PRESETS['vlp16'].elevation_deg  # also the XT16's table
  cases = [('Velodyne VLP-16', 'vlp16_ring.pcd', None),
           ('Hesai PandarXT16', 'pandar_xt16_channel.pcd', None),
           ('Ouster OS1-128', os.path.basename(OUSTER_PCAP), OUSTER_JSON)]
  out, panels = {}, []
  for label, name, meta in cases:
    path = os.path.join(SAMPLES, name)
    if not os.path.isfile(path):
      print(f'{label}: {path} absent, skipped')
      continue
    try:
      fields = read_points(path)
    except UserError as e:
      print(f'{label}: skipped: {e}')
      continue
    ring = ring_field(fields)
    reference = (sensor_lib.from_ouster_metadata(meta) if meta else None)
    row = {'file': name, 'points': int(len(fields['x'])), 'estimates': {}}
    for how, given in (('ring field', fields),
                       ('no ring field', {k: v for k, v in fields.items()
                                          if k not in ('ring', 'channel')})):
      t = time.perf_counter()
      fit = estimate.estimate([given], name=label)
      seconds = time.perf_counter() - t
      el = np.asarray(fit.spec.elevation_deg)
      table = np.asarray(reference.elevation_deg if reference else published)
      err = float(np.abs(el - table).mean()) if len(el) == len(table) else None
      row['estimates'][how] = {
          'beams': fit.spec.height, 'inferred': fit.beams_inferred, 'seconds': seconds,
          'mean_abs_elevation_error_deg': err, 'firings': fit.firings,
          'agreement': fit.agreement}
      if how == 'ring field':
        spec = reference or fit.spec
    spec = dataclasses.replace(spec, width=min(1024, spec.native_width) // 16 * 16)
    a = unfolding.unfold(fields, spec, ring=ring, source=path)
    b = unfolding.unfold(fields, spec, source=path)
    xyz = np.stack([fields[k] for k in 'xyz'], 1).astype(np.float64)
    r = np.linalg.norm(xyz, axis=1)
    ok = np.isfinite(r) & (r > 0)
    rows_b, _ = unfolding.nearest_beam(xyz[ok, 2] / r[ok], r[ok], spec)
    rows_a = np.array([a.ring_rows[int(i)] for i in ring[ok]])
    row.update(spec=spec.name, shape=list(spec.shape),
               rows_agree=float(np.mean(rows_a == rows_b)),
               pixels_equal=float(np.mean(a.depth == b.depth)), unfold=a.summary())
    out[label] = row
    panels.append((label, spec, a.depth, row))
    e = row['estimates']
    print(f'{label}: {row["points"]} points, {spec.height}x{spec.width}; rows without the '
          f'ring field agree for {100 * row["rows_agree"]:.2f}% of points, '
          f'{100 * row["pixels_equal"]:.2f}% of pixels equal')
    for how, v in e.items():
      err = v['mean_abs_elevation_error_deg']
      print(f'  estimate, {how}: {v["beams"]} beams ({len(v["inferred"])} inferred), '
            f'mean |elevation error| {"n/a" if err is None else f"{err:.5f}"} deg, '
            f'{v["firings"]} firings, {v["seconds"]:.2f} s')
  if panels:
    draw(panels, picture)
    print('wrote', picture)
  return out


def draw(panels, path: str):
  """One titled panel per sweep, range on a log scale, one colour bar in m."""
  from matplotlib import colormaps, colors
  from matplotlib.figure import Figure
  heights = [max(0.9, 6.5 * s.height / s.width) for _, s, _, _ in panels]
  fig = Figure(figsize=(8, sum(heights) + 0.5 * len(panels) + 0.8), layout='constrained')
  axes = fig.subplots(len(panels), 1, height_ratios=heights, squeeze=False)[:, 0]
  norm = colors.LogNorm(0.5, 120.0)
  cmap = colormaps['turbo_r'].with_extremes(bad='black')
  for ax, (label, spec, depth, row) in zip(axes, panels):
    shown = ax.imshow(np.ma.masked_equal(depth, 0), cmap=cmap, norm=norm,
                      interpolation='nearest', aspect='auto')
    ax.set_title(f'{label} ({row["file"]}): {spec.height} x {spec.width}, rows by its ring '
                 f'field; by elevation alone {100 * row["pixels_equal"]:.2f}% of pixels equal',
                 fontsize=8)
    ax.set_xticks([])
    ax.set_yticks([0, spec.height - 1], labels=[f'{spec.elevation_deg[0]:+.1f} deg',
                                                f'{spec.elevation_deg[-1]:+.1f} deg'],
                  fontsize=7)
  bar = fig.colorbar(shown, ax=list(axes), location='bottom', fraction=0.05, aspect=40)
  ticks = [0.5, 1, 2, 5, 10, 20, 50, 100]
  bar.set_ticks(ticks, labels=[f'{t:g}' for t in ticks])
  bar.minorticks_off()
  bar.set_label('range (m); black: no return', fontsize=8)
  fig.savefig(path, dpi=100)


if __name__ == '__main__':
  main()
