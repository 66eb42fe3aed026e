"""Why do a run's point-drops collapse? Probes its discriminator with ground truth.

    python benchmarks/research/drops/diagnose_drops.py --workdir RUN [--step N] [--num 64]

For a run trained on simulated scans, the simulator knows each training
scan's complete depth. Feeding the run's discriminator the same scenes
with and without their drops tells whether it can see drops at all:

  * ``observed``: real scans as trained on (drops at ALPHA);
  * ``filled``: the same scans with every dropped pixel that hit a surface
    filled with its complete depth (sky stays ALPHA): a drop-free scan;
  * ``fake`` / ``fake_filled``: the generator's samples with their sampled
    mask, and with the mask all ones (x_tilde itself).

If D scores ``filled`` like ``observed``, it does not see drops, and G has no
reason to keep them. Also the mean D input-gradient on real scans at dropped
pixels vs returned ones, and what the generator's drops look like (rate,
where). Prints a table; ``--json`` writes it (with the machine it ran on).

    python benchmarks/research/drops/diagnose_drops.py --can-d-see-drops [--steps 300]

asks the question without a generator: a fresh discriminator of the study's
CPU scale is trained for ``--steps`` to tell real scans (label real) from
the same scans with their drops filled (label fake), with the run's loss,
DiffAugment and R1, under several settings (R1 gamma, augmentation, width);
the held-out logit gap and accuracy say whether drops alone are visible to it.

    python benchmarks/research/drops/diagnose_drops.py --runs NAME=RUN_DIR,... --plot OUT.png

plots the generated and real drop rates of training runs against the step
(from their metrics.jsonl) and writes them with --json (under 'runs').
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

# benchmarks/ holds common.py, shared with the product benchmarks.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..'))
import common


SETTINGS = {
    'authors (R1 1, DiffAugment)': {},
    'R1 gamma 0.1': {'r1_gamma': 0.1},
    'R1 off': {'r1_gamma': 0.0},
    'no DiffAugment': {'augment': ''},
    'R1 off, no DiffAugment': {'r1_gamma': 0.0, 'augment': ''},
    'paper width (64..512)': {'ch_base': 64, 'ch_max': 512},
    'brightness only': {'augment': 'brightness'},
    'contrast only': {'augment': 'contrast'},
    'translation only': {'augment': 'translation'},
    'cutout only': {'augment': 'cutout'},
    'translation, cutout': {'augment': 'translation,cutout'},
    'symmetric style (all four)': {'augment_style': 'symmetric'},
}


def filled_scans(d, split, sensor, num, offset=0):
  """(observed, drop-filled) normalised scans of a simulated split."""
  from dusty_jax import codec
  from dusty_jax.data import arrays
  sl = slice(offset, offset + num)
  obs = np.asarray(arrays.load_split(d, split, sensor)[sl])
  comp = np.asarray(arrays.load_split(d, split, sensor, 'complete')[sl])
  x_obs = np.asarray(codec.encode(obs, sensor))
  x_fill = np.where(x_obs <= codec.ALPHA,
                    np.asarray(codec.encode(comp, sensor)), x_obs)
  return x_obs, x_fill


def can_d_see_drops(steps: int, batch: int = 16, seed: int = 0, only=None):
  """D-only training: observed (real) vs drop-filled (fake) scans."""
  import optax
  import tqdm
  from dusty_jax import augment, configs, losses, sensor as sensor_lib, trainer
  from dusty_jax.data import pipeline
  base = configs.study('dusty1')
  sensor = sensor_lib.from_config(base.sensor)
  d = pipeline.dataset_dir(base, sensor, log=print)
  tr_obs, tr_fill = filled_scans(d, 'train', sensor, 1024)
  va_obs, va_fill = filled_scans(d, 'val', sensor, 128)
  out = {}
  for name, over in SETTINGS.items():
    if only and name not in only:
      continue
    c = configs.study('dusty1')
    c.update(over)
    setup = trainer.make_setup(c, sensor)
    params = setup.discriminator.init(jax.random.key(seed), jnp.zeros((1,) + sensor.shape))
    tx = setup.d_tx
    opt = tx.init(params)
    policy = tuple(p for p in c.augment.split(',') if p)

    def loss_fn(p, real, fake, key):
      kr, kf = jax.random.split(key)
      ra = augment.per_example(jax.random.split(kr, len(real)), real, policy,
                               setup.augment_style)
      fa = augment.per_example(jax.random.split(kf, len(fake)), fake, policy,
                               setup.augment_style)
      d_fn = lambda x: setup.discriminator.apply(p, x)
      loss = losses.d_loss(d_fn(ra), d_fn(fa))
      if c.r1_gamma > 0:
        loss = loss + 0.5 * c.r1_gamma * losses.r1_penalty(d_fn, ra)
      return loss

    @jax.jit
    def step(p, o, real, fake, key):
      g = jax.grad(loss_fn)(p, real, fake, key)
      u, o = tx.update(g, o, p)
      return optax.apply_updates(p, u), o

    rng = np.random.default_rng(seed)
    for i in tqdm.trange(steps, desc=name, leave=False):
      idx = rng.integers(0, len(tr_obs), batch)
      # Different scenes on each side, so D cannot compare pairs.
      idx2 = rng.integers(0, len(tr_obs), batch)
      params, opt = step(params, opt, tr_obs[idx], tr_fill[idx2], jax.random.key(i))
    d_fn = jax.jit(lambda x: setup.discriminator.apply(params, x))
    lo, lf = np.asarray(d_fn(va_obs)), np.asarray(d_fn(va_fill))
    out[name] = {'logit_observed': float(lo.mean()), 'logit_filled': float(lf.mean()),
                 'gap': float(lo.mean() - lf.mean()),
                 'accuracy': float(((lo > 0).mean() + (lf <= 0).mean()) / 2)}
    print(f'{name:32s} held-out logit observed {lo.mean():7.3f}  filled '
          f'{lf.mean():7.3f}  gap {lo.mean() - lf.mean():7.3f}  accuracy '
          f'{out[name]["accuracy"]:.3f}', flush=True)
  return out


def trajectories(runs: dict, plot: str):
  """{name: run dir} -> {name: {'step', 'drop_rate', 'real_drop_rate', ...}}."""
  import os
  out = {}
  for name, d in runs.items():
    recs = {}
    with open(os.path.join(d, 'metrics.jsonl')) as f:
      for line in f:
        m = json.loads(line)
        recs[m['step']] = m  # the last record of a step wins
    steps = sorted(recs)
    out[name] = {k: [recs[s][k] for s in steps] for k in
                 ('drop_rate', 'real_drop_rate', 'd_real', 'd_fake')}
    out[name]['step'] = steps
  if plot:
    plt = common.pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, r in out.items():
      ax.plot(r['step'], r['drop_rate'], label=name)
    first = next(iter(out.values()))
    ax.plot(first['step'], first['real_drop_rate'], 'k:', label='real scans')
    ax.set_xlabel('training step (batch 16)')
    ax.set_ylabel('drop rate of generated scans')
    ax.set_title('DUSty-I at the CPU scale: point-drops collapse')
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(plot, dpi=120)
    plt.close(fig)
  return out


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument('--runs', default='', help='NAME=DIR,... training runs to plot')
  ap.add_argument('--plot', default='')
  ap.add_argument('--workdir')
  ap.add_argument('--step', type=int, default=None)
  ap.add_argument('--num', type=int, default=64)
  ap.add_argument('--json', default='')
  ap.add_argument('--can-d-see-drops', action='store_true')
  ap.add_argument('--steps', type=int, default=300)
  ap.add_argument('--settings', default='', help='names separated by ; (default: all)')
  a = ap.parse_args(argv)
  common.print_banner()
  if a.runs:
    runs = dict(item.split('=', 1) for item in a.runs.split(','))
    out = trajectories(runs, a.plot)
    for name, r in out.items():
      print(f'{name:40s} drop rate at steps {r["step"][::10]}: '
            + ' '.join(f'{v:.3f}' for v in r['drop_rate'][::10]))
    if a.json:
      common.write_json(a.json, {'runs': out}, indent=None)
    return
  if a.can_d_see_drops:
    out = can_d_see_drops(a.steps, only=[s for s in a.settings.split(';') if s])
    if a.json:
      common.write_json(a.json, {'settings': out}, indent=1)
    return
  if not a.workdir:
    ap.error('--workdir is required (or --can-d-see-drops)')
  from dusty_jax import checkpoint, codec, configs, models, sensor as sensor_lib, trainer
  from dusty_jax.data import arrays, pipeline

  config = configs.load(a.workdir)
  sensor = sensor_lib.from_config(config.sensor)
  setup = trainer.make_setup(config, sensor)
  target = trainer.init_state(setup, jax.random.key(0))
  mngr = checkpoint.manager(a.workdir, keep=config.keep_checkpoints)
  step = mngr.latest_step() if a.step is None else a.step
  state = checkpoint.restore(mngr, step, target)
  d = pipeline.dataset_dir(config, sensor, log=print)
  x_obs, x_fill = filled_scans(d, 'train', sensor, a.num)
  comp = np.asarray(arrays.load_split(d, 'train', sensor, 'complete')[:a.num])
  d_fn = jax.jit(lambda x: setup.discriminator.apply(state.d_params, x))
  z = jax.random.normal(jax.random.key(1), (a.num, config.latent_dim))
  keys = jax.random.split(jax.random.key(2), a.num)
  fake = jax.jit(lambda z: trainer.fake_scans(setup, state.g_params, z, keys))(z)
  grad = jax.jit(jax.grad(lambda x: d_fn(x).sum()))(jnp.asarray(x_obs))
  dropped = (x_obs <= codec.ALPHA) & (comp > 0)
  rows = {
      'step': int(step),
      'd_observed': float(d_fn(x_obs).mean()),
      'd_filled': float(d_fn(x_fill).mean()),
      'd_fake': float(d_fn(fake['scan']).mean()),
      'd_fake_filled': float(d_fn(fake['inv_depth']).mean()),
      'grad_abs_at_drops': float(np.abs(grad)[dropped].mean()),
      'grad_abs_at_returns': float(np.abs(grad)[x_obs > codec.ALPHA].mean()),
      'grad_sign_at_drops': float(np.mean(np.sign(grad)[dropped])),
      'real_drop_rate': float((x_obs <= codec.ALPHA).mean()),
      'fake_drop_rate': float((fake['mask'] < 0.5).mean()),
      'real_mean_x': float(x_obs.mean()),
      'fake_mean_x': float(np.asarray(fake['scan']).mean()),
      'fake_mean_x_tilde': float(np.asarray(fake['inv_depth']).mean()),
  }
  variant = models.get_variant(config.model)
  if variant.has_measurability:
    p = np.asarray(variant.measurability(fake['logit']))
    rows['fake_measurability_mean'] = float(p.mean())
    rows['fake_drop_rate_by_row_top_mid_bottom'] = [
        float(1 - p[:, r].mean()) for r in (0, sensor.height // 2, sensor.height - 1)]
  for k, v in rows.items():
    print(f'{k:40s} {v}')
  if a.json:
    common.write_json(a.json, rows, indent=1)


if __name__ == '__main__':
  main()
