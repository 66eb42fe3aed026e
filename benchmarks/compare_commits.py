"""The train step's speed at two commits, measured in one run, alternating.

    python benchmarks/compare_commits.py --before REV [--after REV] [--rounds 3]
        [--impls matmul] [--repeats 5]

Checks out both commits' libraries into temporary git worktrees and runs
this checkout's benchmarks/train_step.py against each in turn (before,
after, before, after, ...), so that load on a shared machine falls on both
alike. Prints per round and the median over rounds of each commit's
seconds per step (R1 on and off) and the ratio after / before; writes
benchmarks/results/compare_commits.json.

Timings on a shared machine are noisy; ``--hlo`` first answers the sharper
question of whether the two commits compile the train step to the same
program: it compiles each of HLO_CONFIGS (a small DUSty-I step with R1
every step and lazy R1; the study's CPU-scale DUSty-I with the authors'
training and with the 'dips' drops preset) with each commit and compares
XLA's optimised HLO instruction by instruction, names, numbers and source
locations left out: the whole step ('step') and the state update alone,
its logged metrics left to dead-code elimination ('update'). Identical
programs run at the same speed whatever the timings say. The configs are
built by this checkout (experiments/study.py's recipes) and read by each
commit as they are.
``--before`` and ``--after`` also take a directory holding a checkout
(``--after .``: this working tree as it is); ``--rounds 0`` skips the
timings. Where the programs differ,
``--outputs`` shows whether they compute the same function: each commit
computes, on the same inputs (DUSty-I, channels 16..64, batch 4), the generator's
outputs and the gradients of G's loss, D's loss and the R1 penalty with
respect to every parameter, and the largest difference relative to each
array's largest magnitude is printed (float32 rounding: ~1e-6).
``--scales study`` times the CPU study's scale instead of the paper's.
"""

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile

import numpy as np

import common
from dusty_jax import configs

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def git(*args) -> str:
  return subprocess.run(['git', '-C', ROOT, *args], check=True, capture_output=True,
                        text=True).stdout.strip()


def measure(tree: str, args, out: str) -> dict:
  """{(impl, variant, r1): median s} of one train_step.py run on ``tree``."""
  env = dict(os.environ, PYTHONPATH=tree)
  cmd = [sys.executable, os.path.join(HERE, 'train_step.py'), '--out', out,
         '--impls', args.impls, '--variants', args.variants, '--repeats',
         str(args.repeats), '--model', args.model,
         '--scales', args.scales]
  subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL)
  with open(out) as f:
    rows = json.load(f)['rows']
  return {f'{r["impl"]} {r["variant"]} R1={"on" if r["r1"] else "off"}': r['median_s']
          for r in rows}


# Compiles the train step of a config (JSON, argv[1]) with the library on
# PYTHONPATH, whole (argv[2] 'step') or its state update alone ('update'),
# and prints its optimised HLO instructions, canonicalised (no names,
# numbers or locations).
HLO_SNIPPET = r"""
import json, re, sys, jax, ml_collections, numpy as np
from dusty_jax import parallel, trainer
from dusty_jax.sensor import from_config
c = ml_collections.ConfigDict(json.loads(sys.argv[1]))
sensor = from_config(c.sensor)
setup = trainer.make_setup(c, sensor)
fn = trainer.step_fn(setup)
if sys.argv[2] == 'update':
  fn = (lambda step: lambda *a: (step(*a)[0], {}))(fn)
mesh = parallel.data_mesh()
step = parallel.data_parallel(fn, mesh)
state = parallel.replicate(trainer.init_state(setup, jax.random.key(0)), mesh)
x = parallel.shard_batch(np.zeros((c.batch_size,) + sensor.shape, np.float32), mesh)
text = step.lower(state, x, jax.random.key(1)).compile().as_text()
for line in text.splitlines():
  if '=' in line and '(' in line and not re.search(r'file_name_id|file_location_id', line):
    line = re.sub(r'metadata=\{[^}]*\}|, stack_frame_id=\d+', '', line)
    line = re.sub(r'%[\w.\-]+', '%x', line)  # names follow Python function names
    print(re.sub(r'[0-9]+', 'N', line))
"""


def _small(r1_every: int):
  c = configs.default()
  c.model, c.impl, c.batch_size, c.r1_every = 'dusty1', 'matmul', 4, r1_every
  c.latent_dim, c.ch_base, c.ch_max = 32, 8, 32
  return c


def _study(model, preset):
  c = common.experiment('study')['study'](model, preset, 'cpu')
  c.impl = 'matmul'
  return c


# name -> config whose step --hlo compiles.
HLO_CONFIGS = {
    'small dusty1, R1 every 1': lambda: _small(1),
    'small dusty1, R1 every 4': lambda: _small(4),
    'study dusty1,authors,cpu': lambda: _study('dusty1', 'authors'),
    'study dusty1,dips,cpu': lambda: _study('dusty1', 'dips'),
}


# The same function? Outputs and gradients of a small DUSty-I on fixed
# inputs, saved to an .npz (argv[1]).
OUTPUTS_SNIPPET = r"""
import sys, jax, jax.numpy as jnp, numpy as np
from flax import traverse_util
from dusty_jax import configs, losses, trainer
from dusty_jax.sensor import get_sensor
c = configs.default()
c.model, c.impl, c.batch_size = 'dusty1', 'matmul', 4
c.latent_dim, c.ch_base, c.ch_max = 32, 16, 64  # ch_base 16: the head's col2im path
sensor = get_sensor('kitti')
setup = trainer.make_setup(c, sensor)
st = trainer.init_state(setup, jax.random.key(0))
z = jax.random.normal(jax.random.key(1), (4, c.latent_dim))
keys = jax.random.split(jax.random.key(2), 4)
real = jax.random.uniform(jax.random.key(3), (4,) + sensor.shape, minval=-1.0)
d = lambda p, x: setup.discriminator.apply(p, x)
fake = lambda gp: trainer.fake_scans(setup, gp, z, keys)['scan']
out = {'fake': fake(st.g_params)}
grads = {
    'g_loss': jax.grad(lambda gp: losses.g_loss(d(st.d_params, fake(gp))))(st.g_params),
    'd_loss': jax.grad(lambda dp: losses.d_loss(d(dp, real), d(dp, fake(st.g_params))))(
        st.d_params),
    'r1': jax.grad(lambda dp: losses.r1_penalty(lambda x: d(dp, x), real))(st.d_params)}
for name, g in grads.items():
  for k, v in traverse_util.flatten_dict(g, sep='/').items():
    out[f'{name}:{k}'] = v
np.savez(sys.argv[1], **{k: np.asarray(v) for k, v in out.items()})
"""


def same_function(trees: dict, tmp: str) -> dict:
  """{array: largest |after - before| / largest |before|} of OUTPUTS_SNIPPET."""
  arrays = {}
  for name, tree in trees.items():
    path = os.path.join(tmp, f'{name}_outputs.npz')
    env = dict(os.environ, PYTHONPATH=tree, JAX_PLATFORMS='cpu')
    subprocess.run([sys.executable, '-c', OUTPUTS_SNIPPET, path], env=env, cwd=tree,
                   check=True, capture_output=True, text=True)
    arrays[name] = dict(np.load(path))
  b, f = arrays['before'], arrays['after']
  if set(b) != set(f):
    raise RuntimeError(f'the commits compute different arrays: {sorted(set(b) ^ set(f))}')
  return {k: float(np.abs(f[k] - b[k]).max() / max(np.abs(b[k]).max(), 1e-30))
          for k in sorted(b)}


def compiled_program(tree: str, config, what: str = 'step') -> list:
  """The canonical HLO lines of ``config``'s train step compiled in ``tree``
  (``what``: 'step', or 'update' without the metrics)."""
  # In the tree: `python -c` puts the working directory ahead of PYTHONPATH.
  env = dict(os.environ, PYTHONPATH=tree, JAX_PLATFORMS='cpu')
  env.pop('XLA_FLAGS', None)  # one CPU device in both
  code = HLO_SNIPPET + "\nprint('LIBRARY', __import__('dusty_jax').__file__)"
  run = subprocess.run([sys.executable, '-c', code, config.to_json(), what], env=env,
                       cwd=tree, capture_output=True, text=True)
  if run.returncode:
    raise RuntimeError(f'compiling in {tree} failed:\n{run.stderr[-3000:]}')
  out = run.stdout
  lines = out.splitlines()
  library = [l.split(' ', 1)[1] for l in lines if l.startswith('LIBRARY ')]
  if not library or not os.path.realpath(library[0]).startswith(os.path.realpath(tree)):
    raise RuntimeError(f'compiled with {library} instead of the library in {tree}')
  return [l for l in lines if not l.startswith(('N "', 'LIBRARY '))]


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--before', required=True)
  p.add_argument('--after', default='HEAD')
  p.add_argument('--rounds', type=int, default=3)
  p.add_argument('--impls', default='matmul')
  p.add_argument('--variants', default='authors')
  p.add_argument('--model', default='dusty1')
  p.add_argument('--repeats', type=int, default=5)
  p.add_argument('--scales', default='paper', choices=('paper', 'study'))
  p.add_argument('--outputs', action='store_true',
                 help='compare outputs and gradients on fixed inputs before timing')
  p.add_argument('--hlo', action='store_true',
                 help='compare the compiled programs (HLO_CONFIGS) before timing')
  p.add_argument('--hlo_configs', default='',
                 help='with --hlo: only the HLO_CONFIGS whose name holds one of these '
                      '(comma-separated)')
  p.add_argument('--hlo_what', default='step,update',
                 help="with --hlo: 'step' (whole), 'update' (without the metrics) or both")
  p.add_argument('--out', default=os.path.join(HERE, 'results', 'compare_commits.json'))
  a = p.parse_args()
  common.print_banner()
  revs = {n: os.path.abspath(r) if os.path.isdir(r) else git('rev-parse', '--short', r)
          for n, r in (('before', a.before), ('after', a.after))}
  for n, r in revs.items():
    what = 'a checkout on disk' if os.path.isdir(r) else git('log', '-1', '--format=%s', r)[:60]
    print(f'{n:6s} {r} ({what})')
  runs = {'before': [], 'after': []}
  hlo = rel = None
  with tempfile.TemporaryDirectory() as tmp:
    trees = {}
    for name, rev in revs.items():
      if os.path.isdir(rev):
        trees[name] = rev
        continue
      trees[name] = os.path.join(tmp, name)
      git('worktree', 'add', '--detach', trees[name], rev)
    try:
      if a.hlo:
        hlo = {}
        wanted = [w for w in a.hlo_configs.split(',') if w]
        for name, make in HLO_CONFIGS.items():
          if wanted and not any(w in name for w in wanted):
            continue
          for what in a.hlo_what.split(','):
            progs = {n: compiled_program(trees[n], make(), what) for n in trees}
            same = progs['before'] == progs['after']
            only = {n: len(set(progs[n]) - set(progs[o]))
                    for n, o in (('before', 'after'), ('after', 'before'))}
            hlo[f'{name}: {what}'] = dict(
                identical=same, instructions=[len(progs['before']), len(progs['after'])],
                sha256={n: hashlib.sha256('\n'.join(p).encode()).hexdigest()[:16]
                        for n, p in progs.items()},
                distinct_lines_only_in=only)
            print(f'compiled train step ({name}, {what}): {len(progs["before"])} vs '
                  f'{len(progs["after"])} HLO instructions, '
                  f'{"identical" if same else "DIFFERENT"}'
                  + ('' if same else f' (distinct lines only before / after: '
                                     f'{only["before"]} / {only["after"]})'), flush=True)
      if a.outputs:
        rel = same_function(trees, tmp)
        worst = max(rel, key=rel.get)
        print(f'outputs and gradients (DUSty-I 16..64, {len(rel)} arrays): largest '
              f'relative difference {rel[worst]:.2e} ({worst})', flush=True)
      for r in range(a.rounds):
        for name in ('before', 'after'):
          res = measure(trees[name], a, os.path.join(tmp, f'{name}_{r}.json'))
          runs[name].append(res)
          print(f'round {r + 1} {name:6s} ' + ', '.join(
              f'{k}: {v:.2f} s' for k, v in res.items()), flush=True)
    finally:
      for name, t in trees.items():
        if not os.path.isdir(revs[name]):
          git('worktree', 'remove', '--force', t)
  summary = {}
  for k in (runs['before'][0] if runs['before'] else {}):
    b = statistics.median(x[k] for x in runs['before'])
    f = statistics.median(x[k] for x in runs['after'])
    summary[k] = dict(before_s=b, after_s=f, ratio=f / b)
    print(f'{k}: before {b:.2f} s, after {f:.2f} s per step (median of {a.rounds} '
          f'rounds); after / before = {f / b:.3f}')
  common.write_json(a.out, dict(revisions=revs, args=vars(a), runs=runs, summary=summary,
                                identical_hlo=hlo, relative_difference=rel))


if __name__ == '__main__':
  main()
