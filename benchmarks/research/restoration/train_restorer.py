"""Trains the learned fill (dusty_jax/restorer.py) on the simulator's
training scans, each corrupted at random, and saves its variables.

    python benchmarks/research/restoration/train_restorer.py \
        --data ~/.cache/dusty_jax/synthetic/kitti_64x256_n2000_s0 --out restorer.npz \
        --num 500 --steps 1000 --width 24 --ce 0.05 --lr 2e-3

(the shipped pretrained/restorers/sim-hdl64e.npz: 12 min on the 2-core VM).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
import tqdm

from dusty_jax import codec, restorer
from dusty_jax.data import arrays


def random_known(rng, shape):
  """A random corruption's known mask: every K-th row (K in 2, 4, 8, any
  offset) or random pixels kept (10-50%)."""
  if rng.uniform() < 0.5:
    k = int(rng.choice([2, 4, 8]))
    known = np.zeros(shape, bool)
    known[rng.integers(k)::k] = True
    return known
  return rng.uniform(size=shape) >= rng.uniform(0.5, 0.95)


def build(depth, sensor, rng):
  known = np.stack([random_known(rng, d.shape) for d in depth])
  cands, inputs = zip(*(restorer.features(d, k, sensor)
                        for d, k in tqdm.tqdm(zip(depth, known), total=len(depth),
                                              desc='features', file=sys.stderr)))
  cands, inputs = np.stack(cands), np.stack(inputs)
  valid = np.asarray(codec.valid_depth(depth, sensor))
  return inputs, cands, depth.astype(np.float32), valid & ~known


def main():
  p = argparse.ArgumentParser()
  p.add_argument('--data', required=True)
  p.add_argument('--out', required=True)
  p.add_argument('--num', type=int, default=2000)
  p.add_argument('--steps', type=int, default=2000)
  p.add_argument('--batch', type=int, default=16)
  p.add_argument('--crop', type=int, default=64)
  p.add_argument('--width', type=int, default=32)
  p.add_argument('--cache', default='', help='an .npz for the features, kept between runs')
  p.add_argument('--lr', type=float, default=1e-3)
  p.add_argument('--ce', type=float, default=0.0, help='weight of the best-candidate '
                 'cross-entropy beside AbsRel')
  a = p.parse_args()
  import dusty_jax
  params = dusty_jax.load_pretrained('sim-dusty1')
  sensor = params.sensor
  depth = np.asarray(arrays.load_split(a.data, 'train', sensor)[:a.num], np.float32)
  rng = np.random.default_rng(0)
  if a.cache and os.path.isfile(a.cache):  # the features of an earlier run (same flags)
    with np.load(a.cache) as f:
      inputs, cands, target, mask = (f[k] for k in ('inputs', 'cands', 'target', 'mask'))
  else:
    inputs, cands, target, mask = build(depth, sensor, rng)
    if a.cache:
      np.savez(a.cache, inputs=inputs, cands=cands, target=target, mask=mask)
  settings = restorer.Settings(width=a.width)
  net = restorer.Selector(settings)
  variables = net.init(jax.random.key(0), jnp.zeros((1, 64, a.crop, inputs.shape[-1])))
  tx = optax.adam(optax.cosine_decay_schedule(a.lr, a.steps))
  opt = tx.init(variables)

  def loss_fn(variables, x, c, t, m):
    """AbsRel of the answer, plus ``--ce`` x the cross-entropy of the
    weights against each pixel's best candidate (a per-pixel signal where
    the candidates' AbsRel differs by little)."""
    logits = restorer.Selector(settings).apply(variables, x)
    pred = restorer.uncode(restorer.combine(logits, c), sensor)
    denom = jnp.maximum(m.sum(), 1)
    safe_t = jnp.where(m, t, 1.0)
    absrel = jnp.sum(jnp.where(m, jnp.abs(pred - t) / safe_t, 0.0)) / denom
    if not a.ce:
      return absrel
    errs = jnp.abs(restorer.uncode(c, sensor) - safe_t[..., None]) / safe_t[..., None]
    best = jax.nn.one_hot(jnp.argmin(errs, -1), c.shape[-1])
    ce = -jnp.sum(best * jax.nn.log_softmax(logits, -1), -1)
    return absrel + a.ce * jnp.sum(jnp.where(m, ce, 0.0)) / denom

  @jax.jit
  def step(variables, opt, x, c, t, m):
    loss, g = jax.value_and_grad(loss_fn)(variables, x, c, t, m)
    updates, opt = tx.update(g, opt, variables)
    return optax.apply_updates(variables, updates), opt, loss

  w = inputs.shape[2]
  losses, t0 = [], time.time()
  for i in (bar := tqdm.trange(a.steps, file=sys.stderr)):
    idx = rng.integers(len(inputs), size=a.batch)
    c0 = int(rng.integers(w))
    cols = (np.arange(a.crop) + c0) % w
    variables, opt, loss = step(variables, opt, inputs[idx][:, :, cols], cands[idx][:, :, cols],
                                target[idx][:, :, cols], mask[idx][:, :, cols])
    losses.append(float(loss))
    if i % 50 == 0:
      bar.set_postfix(loss=f'{np.mean(losses[-50:]):.4f}')
  meta = {'training': {'data': a.data, 'num': a.num, 'steps': a.steps, 'batch': a.batch,
                       'crop': a.crop, 'lr': a.lr, 'ce': a.ce, 'seconds': time.time() - t0,
                       'final_loss': float(np.mean(losses[-100:])),
                       'corruptions': 'beams:K (K in 2, 4, 8, any offset) or drop:F '
                                      '(F in 0.5-0.95), half each',
                       'script': 'benchmarks/research/restoration/train_restorer.py'}}
  restorer.save(a.out, variables, settings, sensor, meta)
  print(json.dumps(meta))


if __name__ == '__main__':
  main()
