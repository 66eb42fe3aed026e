"""Simulated-LiDAR speed: where a 64x256 scan's time goes, and the default data's.

    python benchmarks/synthesize.py [--num 60] [--workers 2] [--baseline DIR] [--full] [--main]

1. Phases, one process, CPU seconds (time.process_time) per scan, median over
   --num scans: building the scene, casting the rays (each ray caster), the
   rest of render_scan (drop model, noise), the whole scan.
2. Worker start-up: wall seconds from starting a pool of --workers spawned
   processes (spawned, as under JAX) until each has returned a result.
3. With --full: the default data (synthetic.write_dataset, 2,000 + 200 + 200
   scans, --workers processes) into a temporary directory, JAX loaded in the
   parent as under train: wall seconds, with the time spent drawing the
   preview (and, in older trees, the parent's writing of the arrays: the
   workers write them now), and CPU seconds of the parent and its workers
   together (what load does not stretch); --rounds times per tree.
4. With --main: the README's main command in a fresh cache, as a newcomer
   runs it, from its start until the default data is written (its
   meta.json), then stopped; --rounds times per tree.

``--baseline DIR`` (a checkout of older code, e.g. ``git worktree add
/tmp/wt_sim f597033``) measures the same with DIR's dusty_jax, in
subprocesses that alternate with the current tree's, so that both see the
same load; the ratios are what to quote from a loaded machine.
"""

import argparse
import glob
import json
import multiprocessing
import os
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

import common
from dusty_jax.data import arrays, scene, simulated_lidar, synthetic
from dusty_jax.sensor import get_sensor

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
DEFAULT_SPLITS = {'train': 2000, 'val': 200, 'test': 200}  # experiments/synthetic.py


def _cpu(fn):
  t = time.process_time()
  out = fn()
  return time.process_time() - t, out


def _phases(start: int, count: int) -> dict:
  """CPU seconds per scan of each phase, scans start .. start + count - 1."""
  sensor = get_sensor('kitti')
  simulated_lidar.render_scan(start, sensor)  # warm: caches, first imports
  out = {'build': [], 'scan': []}
  # The baseline (before data/embree.py) has one ray caster: trimesh's Embree.
  casters = getattr(simulated_lidar, 'RAYCASTERS', ('pyembree',))
  dirs = simulated_lidar.ray_directions(sensor).reshape(-1, 3)
  for seed in range(start, start + count):
    dt, (mesh, _, _) = _cpu(lambda: scene.build_scene(seed))
    out['build'].append(dt)
    for caster in casters:
      if caster == 'numpy':
        continue  # minutes per scan; the fallback without embreex
      if hasattr(simulated_lidar, 'first_hits'):
        cast = lambda: simulated_lidar.first_hits(mesh, sensor, caster)
      else:
        cast = lambda: simulated_lidar.intersector(mesh).intersects_id(
            np.zeros_like(dirs), dirs, multiple_hits=False, return_locations=True)
      out.setdefault(f'cast_{caster}', []).append(_cpu(cast)[0])
    out['scan'].append(_cpu(lambda: simulated_lidar.render_scan(seed, sensor))[0])
  return out


def _worker_fn():
  # The baseline's worker lived in synthetic.py.
  return getattr(simulated_lidar, 'render_arrays', None) or synthetic._render_arrays


def _startup(workers: int) -> dict:
  """Wall seconds until each of ``workers`` spawned processes has rendered
  one 2x8 scan (as good as nothing), JAX loaded in the parent as under train."""
  import jax  # so that the parent looks like a training run
  jax.devices()
  from dusty_jax.sensor import SensorSpec
  tiny = SensorSpec('tiny', (1.0, -10.0), 8, 8)
  t = time.perf_counter()
  with multiprocessing.get_context('spawn').Pool(workers) as pool:
    pool.map(_worker_fn(), [(i, tiny) for i in range(workers)], chunksize=1)
    return {'startup_s': time.perf_counter() - t}


def _write(out: str, workers: int) -> dict:
  """Wall seconds of write_dataset of the default data, JAX loaded as under
  train, and of its array writes and preview."""
  import jax
  jax.devices()
  spent = {'save_s': 0.0, 'preview_s': 0.0}

  def timed(fn, key):
    def wrapper(*a, **k):
      t = time.perf_counter()
      try:
        return fn(*a, **k)
      finally:
        spent[key] += time.perf_counter() - t
    return wrapper

  def cpu():  # this process and its reaped children (the pool's workers)
    own, kids = (resource.getrusage(w) for w in (resource.RUSAGE_SELF,
                                                 resource.RUSAGE_CHILDREN))
    return own.ru_utime + own.ru_stime, kids.ru_utime + kids.ru_stime

  synthetic.arrays.save_array = timed(arrays.save_array, 'save_s')
  synthetic.save_preview = timed(synthetic.save_preview, 'preview_s')
  t, (own, kids) = time.perf_counter(), cpu()
  synthetic.write_dataset(out, get_sensor('kitti'), 2000, seed=0, splits=DEFAULT_SPLITS,
                          progress=False, workers=workers)
  wall, (own2, kids2) = time.perf_counter() - t, cpu()
  return dict(spent, total_s=wall, parent_cpu_s=own2 - own, workers_cpu_s=kids2 - kids,
              cpu_s=own2 - own + kids2 - kids)


def _main_command(tree: str) -> float:
  """Wall seconds from starting ``python -m dusty_jax.train --config
  experiments/synthetic.py`` in ``tree`` with an empty cache until the
  default data's meta.json exists; the command is then killed."""
  with tempfile.TemporaryDirectory() as tmp:
    env = dict(os.environ, DUSTY_JAX_CACHE=os.path.join(tmp, 'cache'), PYTHONPATH=tree)
    env.pop('JAX_COMPILATION_CACHE_DIR', None)
    meta = os.path.join(tmp, 'cache', 'synthetic', '*', 'meta.json')
    t = time.perf_counter()
    proc = subprocess.Popen([sys.executable, '-m', 'dusty_jax.train', '--config',
                             'experiments/synthetic.py', '--workdir', os.path.join(tmp, 'w')],
                            cwd=tree, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
      while not glob.glob(meta):
        if proc.poll() is not None:
          raise RuntimeError(f'{tree}: the main command ended: {proc.stderr.read()[-2000:]}')
        time.sleep(0.02)
      return time.perf_counter() - t
    finally:
      os.killpg(proc.pid, signal.SIGKILL)
      proc.communicate()


def _run(tree: str, *args) -> dict:
  """One of the modes above in a subprocess, with ``tree``'s dusty_jax."""
  env = dict(os.environ, PYTHONPATH=tree)
  r = subprocess.run([sys.executable, os.path.abspath(__file__), *map(str, args)],
                     cwd=tempfile.gettempdir(), env=env, capture_output=True, text=True)
  if r.returncode:
    raise RuntimeError(f'{tree}: {args}: {r.stderr[-2000:]}')
  return json.loads(r.stdout.strip().splitlines()[-1])


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--num', type=int, default=60, help='scans timed per tree')
  p.add_argument('--rounds', type=int, default=3, help='alternations of the trees')
  p.add_argument('--workers', type=int, default=os.cpu_count() or 1)
  p.add_argument('--baseline', default='', help='a checkout of older code')
  p.add_argument('--full', action='store_true', help='also time the default data')
  p.add_argument('--main', action='store_true',
                 help="also time the README's main command until its data is written")
  p.add_argument('--out', default=os.path.join(HERE, 'results', 'synthesize.json'))
  p.add_argument('--_phases', nargs=2, type=int, help=argparse.SUPPRESS)
  p.add_argument('--_startup', type=int, help=argparse.SUPPRESS)
  p.add_argument('--_write', nargs=2, help=argparse.SUPPRESS)
  a = p.parse_args()
  if a._phases:
    print(json.dumps(_phases(*a._phases)))
    return
  if a._startup:
    print(json.dumps(_startup(a._startup)))
    return
  if a._write:
    print(json.dumps(_write(a._write[0], int(a._write[1]))))
    return

  info = common.print_banner()
  load_start = os.getloadavg()
  trees = {'current': REPO}
  if a.baseline:
    trees['baseline'] = os.path.abspath(a.baseline)
  phases = {name: {} for name in trees}
  per_round = -(-a.num // a.rounds)
  for r in range(a.rounds):  # the trees alternate: the same load for both
    for name, tree in trees.items():
      for k, v in _run(tree, '--_phases', 10_000 + r * per_round, per_round).items():
        phases[name].setdefault(k, []).extend(v)
  startup = {name: [_run(tree, '--_startup', a.workers)['startup_s'] for _ in range(2)]
             for name, tree in trees.items()}
  commits = {name: subprocess.run(['git', '-C', tree, 'rev-parse', '--short', 'HEAD'],
                                  capture_output=True, text=True).stdout.strip()
             for name, tree in trees.items()}
  results = dict(embree=simulated_lidar.has_embree(), workers=a.workers, num=a.num,
                 commits=commits,
                 load_average_start=load_start, trees=trees, phases_ms={}, startup_s={},
                 full={})
  for name in trees:
    ms = {k: statistics.median(v) * 1e3 for k, v in phases[name].items()}
    cast = ms.get('cast_embree', ms['cast_pyembree'])
    ms['rest'] = ms['scan'] - ms['build'] - cast
    results['phases_ms'][name] = ms
    results['startup_s'][name] = min(startup[name])
    print(f'{name:9s} CPU ms per scan (median of {a.num}): ' +
          ', '.join(f'{k} {v:.1f}' for k, v in ms.items()) +
          f'; {a.workers} spawned workers start in {min(startup[name]):.2f} s')
  if a.full:
    runs = {name: [] for name in trees}
    for r in range(a.rounds):
      for name, tree in trees.items():
        with tempfile.TemporaryDirectory() as out:
          runs[name].append(_run(tree, '--_write', out, a.workers))
    for name in trees:
      results['full'][name] = f = {k: statistics.median(run[k] for run in runs[name])
                                   for k in runs[name][0]}
      f['total_s_each'] = [run['total_s'] for run in runs[name]]
      print(f'{name:9s} default data (2,000 + 200 + 200 scans, {a.workers} workers; median '
            f'of {a.rounds}): {f["total_s"]:.1f} s wall, of which the parent writing '
            f'{f["save_s"]:.1f} s, preview {f["preview_s"]:.1f} s; CPU {f["cpu_s"]:.1f} s '
            f'(workers {f["workers_cpu_s"]:.1f} s)')
  if a.main:
    each = {name: [] for name in trees}
    for r in range(a.rounds):
      for name, tree in trees.items():
        each[name].append(_main_command(tree))
    results['main_command_s'] = {name: {'median': statistics.median(v), 'each': v}
                                 for name, v in each.items()}
    for name, v in each.items():
      print(f'{name:9s} main command, start to the default data written (median of '
            f'{a.rounds}): {statistics.median(v):.1f} s ({", ".join(f"{x:.1f}" for x in v)})')
  if a.baseline:
    before, after = results['phases_ms']['baseline'], results['phases_ms']['current']
    ratios = {'scan': before['scan'] / after['scan'], 'build': before['build'] / after['build'],
              'cast': before['cast_pyembree'] / after['cast_embree']}
    if a.full:
      full = results['full']
      ratios['default_data_wall'] = full['baseline']['total_s'] / full['current']['total_s']
      ratios['default_data_cpu'] = full['baseline']['cpu_s'] / full['current']['cpu_s']
    if a.main:
      main_s = results['main_command_s']
      ratios['main_command'] = main_s['baseline']['median'] / main_s['current']['median']
    results['speedup'] = ratios
    print('baseline / current: ' + ', '.join(f'{k} {v:.2f}x' for k, v in ratios.items()))
  results['load_average_end'] = os.getloadavg()
  print(f'load average (1 min) at the start {load_start[0]:.1f}, at the end '
        f'{results["load_average_end"][0]:.1f}, on {info["cpus"]} CPUs')
  common.write_json(a.out, results)


if __name__ == '__main__':
  main()
