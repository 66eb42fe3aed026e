"""Prototype: would a serialised search make a second process's first invert fast?

    pip install flatbuffers   # jax.export's serialisation needs it
    python benchmarks/research/first_call/export_search.py [--model sim-dusty1] [--steps 300]

A second process's first ``invert`` spends most of its time tracing and
lowering the search (benchmarks/README.md, first_call), which the persistent
compilation cache does not skip. This exports inversion._search once
(``jax.export``, the shipped model's variables as arguments, one simulated
scan, the default objective), then in fresh processes that share one
compilation cache: deserialises it and times its first and a warm call,
and the same for inversion._search itself, and checks the two agree bit for
bit. Library code is not changed. Prints a table; writes ``--out`` (JSON).
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(os.path.dirname(HERE)))


def _one(mode: str, path: str, model: str, steps: int) -> dict:
  """In this process: ``mode`` 'export' writes the serialised search to
  ``path``; 'exported' and 'direct' time a first and warm calls."""
  t0 = time.perf_counter()
  import jax
  import jax.numpy as jnp
  import numpy as np
  from jax import export

  import dusty_jax
  from dusty_jax import codec, inversion, xla_cache
  from dusty_jax.data import simulated_lidar
  xla_cache.enable()
  p = dusty_jax.load_pretrained(model)
  depth = simulated_lidar.render_scan(7, p.sensor).depth[None]
  scans = jnp.asarray(codec.encode(depth, p.sensor))
  masks = inversion.target_mask(scans, None)
  keys = jax.random.key_data(jax.random.split(jax.random.key(0), 1))
  z0 = jax.random.normal(jax.random.key(1), (1, p.latent_dim))
  leaves, treedef = jax.tree.flatten(p)
  args = (leaves, scans, masks, z0, keys, jnp.int32(steps), jnp.float32(inversion.LR))

  def search(leaves, scans, masks, z0, keydata, n, lr):
    return inversion._search(jax.tree.unflatten(treedef, leaves), scans, masks, z0,
                             jax.random.wrap_key_data(keydata), n, lr, None,
                             inversion.objective)

  if mode == 'export':
    with open(path, 'wb') as f:
      f.write(export.export(jax.jit(search))(*args).serialize())
    return {}
  load = time.perf_counter() - t0
  if mode == 'exported':
    with open(path, 'rb') as f:
      fn = jax.jit(export.deserialize(bytearray(f.read())).call)
  else:
    fn = jax.jit(search)
  times = []
  for _ in range(4):
    t = time.perf_counter()
    out = fn(*args)
    np.asarray(out['inv_depth'])
    times.append(time.perf_counter() - t)
  np.save(path + f'.{mode}.npy', np.asarray(out['inv_depth']))
  return {'load_s': load, 'first_s': times[0], 'warm_s': statistics.median(times[1:])}


def _run(*args) -> dict:
  r = subprocess.run([sys.executable, os.path.abspath(__file__), *map(str, args)],
                     cwd=REPO, capture_output=True, text=True)
  if r.returncode:
    raise SystemExit(f'{args[1]}: {r.stderr[-2000:]}')
  return json.loads(r.stdout.strip().splitlines()[-1])


def main():
  p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  p.add_argument('--model', default='sim-dusty1')
  p.add_argument('--steps', type=int, default=300)
  p.add_argument('--out', default=os.path.join(HERE, 'results', 'export_search.json'))
  p.add_argument('--_one', nargs=2, help=argparse.SUPPRESS)
  a = p.parse_args()
  if a._one:
    print(json.dumps(_one(a._one[0], a._one[1], a.model, a.steps)))
    return
  sys.path.insert(0, os.path.join(REPO, 'benchmarks'))
  import common
  import numpy as np
  info = common.print_banner()
  with tempfile.TemporaryDirectory() as tmp:
    os.environ['DUSTY_JAX_CACHE'] = tmp  # one compilation cache, empty at the start
    path = os.path.join(tmp, 'search.exported')
    _run('--model', a.model, '--steps', a.steps, '--_one', 'export', path)
    rows = {}
    for mode in ('direct', 'exported'):  # each: a process filling the cache, then a second
      first = _run('--model', a.model, '--steps', a.steps, '--_one', mode, path)
      second = _run('--model', a.model, '--steps', a.steps, '--_one', mode, path)
      rows[mode] = {'first_process': first, 'second_process': second}
    same = bool(np.array_equal(np.load(path + '.direct.npy'), np.load(path + '.exported.npy')))
  print(f'{"search (1 scan, " + str(a.steps) + " steps)":28s} {"process":>8s} {"load s":>7s} '
        f'{"first call s":>13s} {"warm s":>7s}')
  for mode, r in rows.items():
    for k, v in r.items():
      print(f'{mode:28s} {k.split("_")[0]:>8s} {v["load_s"]:7.2f} {v["first_s"]:13.2f} '
            f'{v["warm_s"]:7.2f}')
  print(f'exported and direct results identical: {same}')
  os.makedirs(os.path.dirname(a.out), exist_ok=True)
  with open(a.out, 'w') as f:
    json.dump({'machine': info, 'model': a.model, 'steps': a.steps, 'rows': rows,
               'identical': same}, f, indent=1)
  print(f'wrote {a.out}')


if __name__ == '__main__':
  main()
