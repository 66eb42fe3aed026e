"""The authors' PyTorch DUSty-I step and inversion, timed beside ours.

    python benchmarks/authors_step.py --authors-dir PATH/dusty-gan [--device cuda]
        [--amp] [--batch 32] [--scale paper|study] [--invert 1,32]

Needs torch and a checkout of the authors' code (kazuto1011/dusty-gan;
fetched, never part of this repository): their Generator, Discriminator,
DUSty1 masker, GANLoss and DiffAugment modules are imported from it and
called in their trainer's order (trainers/dcgan_amp.py: D step on
DiffAugmented reals and fakes with R1 gamma/2 every step, then the G step
through the updated D, then the EMA), with ``--amp`` their mixed precision
(their config's ``enable_amp: true``; CUDA only). Their data loading is not
timed (random scans in [-1, 1] with 20% drops at -1). The inversion follows
their evaluate_reconstruction.py: Adam lr 0.1 with their ramp schedule,
latent noise, renormalisation after each step, L1 on [0, 1] inverse depth
over the target's valid pixels, ``--invert-iters`` iterations for a batch.

Prints medians (after one warm-up) and writes JSON to ``--out``.

With ``--train-steps N --data-dir DIR --workdir OUT`` it trains instead: their
step on batches of DIR's training scans (a dusty_jax prepared dataset, e.g.
the simulated one in ~/.cache/dusty_jax/synthetic/...), writing their drop
rate and D logits to OUT/metrics.jsonl, so their training can be set beside
ours (benchmarks/research/drops/drops_screen.py --runs). That needs dusty_jax importable
beside torch (``pip install -e .`` in the torch environment).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import sys
import time
import types

SCALES = {  # latent, ch_base, ch_max: the paper's and the study's CPU scale.
    'paper': (512, 64, 512),
    'study': (128, 16, 128),
}


def load_authors(path: str):
  """(define_G, define_D, GANLoss, DiffAugment) from their checkout."""
  sys.path.insert(0, path)
  from models import define_D, define_G  # their package, torch only.
  from models.loss import GANLoss
  # utils/__init__ imports cv2 and omegaconf: load diff_augment.py alone.
  spec = importlib.util.spec_from_file_location(
      'authors_diff_augment', os.path.join(path, 'utils', 'diff_augment.py'))
  mod = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(mod)
  return define_G, define_D, GANLoss, mod.DiffAugment


def namespace(d):
  return types.SimpleNamespace(**{k: namespace(v) if isinstance(v, dict) and k != 'out_ch'
                                  else v for k, v in d.items()})


def build(define_G, define_D, shape, latent, ch_base, ch_max):
  cfg = namespace({'model': {
      'gen': {'arch': 'dusty1/dcgan_eqlr', 'in_ch': latent,
              'out_ch': {'depth': 1, 'confidence': 1}, 'ch_base': ch_base,
              'ch_max': ch_max, 'shape': shape, 'tau': 1.0, 'drop_const': -1.0},
      'dis': {'arch': 'dcgan_eqlr', 'in_ch': 1, 'ch_base': ch_base, 'ch_max': ch_max,
              'shape': shape},
      'ring': True}})
  return define_G(cfg), define_G(cfg), define_D(cfg)


def sync(torch, device):
  if device.type == 'cuda':
    torch.cuda.synchronize()


def median_time(fn, repeats, torch, device):
  fn()
  sync(torch, device)
  times = []
  for _ in range(repeats):
    t = time.perf_counter()
    fn()
    sync(torch, device)
    times.append(time.perf_counter() - t)
  return statistics.median(times), times


def train_step_fn(torch, G, G_ema, D, A, criterion, batch, latent, shape, device, amp,
                  reals=None):
  """One step in their trainer's order (trainers/dcgan_amp.py).

  ``reals``: a function of the step number returning a (B, 1, H, W) batch
  of real scans (normalised inverse depth, drops at -1); default: one fixed
  random batch. The step returns their logged scalars.
  """
  optim_G = torch.optim.Adam(G.parameters(), lr=0.002, betas=(0.0, 0.99))
  optim_D = torch.optim.Adam(D.parameters(), lr=0.002, betas=(0.0, 0.99))
  scaler = torch.cuda.amp.GradScaler(enabled=amp)
  decay = 0.5 ** (batch / 10000.0)
  gen = torch.Generator(device='cpu').manual_seed(0)
  x = torch.rand(batch, 1, *shape, generator=gen) * 2 - 1
  x = torch.where(torch.rand(x.shape, generator=gen) < 0.2, -1.0, x).to(device)
  autocast = lambda: torch.autocast(device_type=device.type, enabled=amp)

  count = [0]

  def step():
    nonlocal x
    if reals is not None:
      x = reals(count[0]).to(device)
    count[0] += 1
    for p in D.parameters():
      p.requires_grad_(True)
    optim_D.zero_grad(set_to_none=True)
    z = torch.randn(batch, latent, device=device)
    with autocast():
      synth = G(latent=z)
      x_real_aug = A(x).detach().requires_grad_()
      x_fake_aug = A(synth['depth']).detach()
      y_real, y_fake = D(x_real_aug), D(x_fake_aug)
      loss_d = criterion(y_real, y_fake, 'D')
    (grads,) = torch.autograd.grad(scaler.scale(y_real.sum()), [x_real_aug],
                                   create_graph=True, only_inputs=True)
    grads = grads / scaler.get_scale()
    with autocast():
      r1 = (grads ** 2).sum(dim=[1, 2, 3]).mean()
      loss_d = loss_d + 0.5 * r1 + 0.0 * y_real.squeeze()[0]
    scaler.scale(loss_d).backward()
    scaler.step(optim_D)
    for p in D.parameters():
      p.requires_grad_(False)
    optim_G.zero_grad(set_to_none=True)
    with autocast():
      y_real, y_fake = D(A(x).detach()), D(A(synth['depth']))
      loss_g = criterion(y_real, y_fake, 'G')
    scaler.scale(loss_g).backward()
    scaler.step(optim_G)
    scaler.update()
    with torch.no_grad():
      for e, p in zip(G_ema.parameters(), G.parameters()):
        e.copy_(decay * e + (1 - decay) * p)
    return {'drop_rate': float((synth['depth'] <= -1).float().mean()),
            'real_drop_rate': float((x <= -1).float().mean()),
            'd_real': float(y_real.mean()), 'd_fake': float(y_fake.mean()),
            'loss_d': float(loss_d), 'loss_g': float(loss_g)}

  return step


def train(torch, step, num_steps, workdir, log_every):
  """Runs ``step`` and writes their scalars as metrics.jsonl, every
  ``log_every`` steps the mean of those steps (as dusty_jax's trainer logs)."""
  os.makedirs(workdir, exist_ok=True)
  pending = []
  with open(os.path.join(workdir, 'metrics.jsonl'), 'w') as f:
    for i in range(num_steps):
      pending.append(step())
      if (i + 1) % log_every == 0:
        mean = {k: statistics.fmean(m[k] for m in pending) for k in pending[0]}
        f.write(json.dumps(dict(step=i + 1, **mean)) + '\n')
        f.flush()
        pending = []
        if (i + 1) % (10 * log_every) == 0:
          print(f'  step {i + 1}: drop rate {mean["drop_rate"]:.4f}, D {mean["d_real"]:+.2f}'
                f'/{mean["d_fake"]:+.2f}', flush=True)


def real_batches(torch, data_dir, batch, seed):
  """Batches of a prepared dataset's training scans, encoded as the authors'
  fetch_reals does (their invert_depth then sigmoid_to_tanh, drops at -1:
  the formula of dusty_jax.codec.encode, used here), drawn with replacement
  from (seed, step)."""
  import numpy as np
  sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))
  from dusty_jax import codec
  from dusty_jax.data import arrays
  from dusty_jax.sensor import SensorSpec, get_sensor
  meta = json.load(open(os.path.join(data_dir, arrays.META)))
  sensor = (get_sensor(meta['sensor']) if isinstance(meta['sensor'], str)
            else SensorSpec.from_dict(meta['sensor']))
  depth = arrays.load_split(data_dir, 'train', sensor)

  def get(step):
    idx = np.sort(np.random.default_rng([seed, step]).integers(0, len(depth), batch))
    x = np.asarray(codec.encode(np.asarray(depth[idx]), sensor), np.float32)
    return torch.from_numpy(x)[:, None]

  return get


def invert_fn(torch, G, batch, latent, shape, iters, device):
  """Their evaluate_reconstruction.py loop for one batch of targets."""
  gen = torch.Generator(device='cpu').manual_seed(1)
  ref = (torch.rand(batch, 1, *shape, generator=gen)).to(device)  # [0, 1]
  mask = (torch.rand(batch, 1, *shape, generator=gen) > 0.2).float().to(device)

  def schedule(i):
    t = i / iters
    gamma = min(1.0, (1.0 - t) / 0.25)
    gamma = 0.5 - 0.5 * __import__('math').cos(gamma * __import__('math').pi)
    return gamma * min(1.0, t / 0.05)

  def run():
    z = torch.randn(batch, latent, device=device)
    z = z / z.pow(2).mean(dim=1, keepdim=True).add(1e-9).sqrt()
    z = torch.nn.Parameter(z)
    opt = torch.optim.Adam([z], lr=0.1)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_lambda=schedule)
    for i in range(iters):
      w = max(0.0, 1.0 - (i / iters) / 0.75)
      noise = 0.05 * w ** 2 * torch.randn_like(z)
      out = G(z + noise)
      inv = (out['depth_orig'] + 1) / 2
      loss = ((ref - inv).abs() * mask).sum(dim=(1, 2, 3)) / mask.sum(dim=(1, 2, 3))
      opt.zero_grad()
      loss.backward(gradient=torch.ones_like(loss))
      opt.step()
      with torch.no_grad():
        z.div_(z.pow(2).mean(dim=1, keepdim=True).add(1e-9).sqrt())
      sched.step()

  return run


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument('--authors-dir', required=True)
  p.add_argument('--device', default='cpu')
  p.add_argument('--threads', type=int, default=0, help='torch CPU threads (0: default)')
  p.add_argument('--amp', action='store_true')
  p.add_argument('--scale', default='paper', choices=sorted(SCALES))
  p.add_argument('--batch', type=int, default=32)
  p.add_argument('--shape', default='64x256')
  p.add_argument('--repeats', type=int, default=5)
  p.add_argument('--invert', default='1,32', help="batch sizes to invert ('' for none)")
  p.add_argument('--invert-iters', type=int, default=100)
  p.add_argument('--out', default='')
  p.add_argument('--train-steps', type=int, default=0,
                 help='instead of timing: train this many steps on --data-dir')
  p.add_argument('--data-dir', default='', help="prepared scans (dusty_jax's format)")
  p.add_argument('--workdir', default='', help='where --train-steps writes metrics.jsonl')
  p.add_argument('--log-every', type=int, default=10)
  p.add_argument('--seed', type=int, default=0)
  a = p.parse_args(argv)
  if not os.path.isdir(os.path.join(a.authors_dir, 'models')):
    sys.exit(f'error: {a.authors_dir}: not a checkout of kazuto1011/dusty-gan '
             '(no models/)')
  import torch
  if a.threads:
    torch.set_num_threads(a.threads)
  device = torch.device(a.device)
  define_G, define_D, GANLoss, DiffAugment = load_authors(a.authors_dir)
  shape = tuple(int(v) for v in a.shape.split('x'))
  latent, ch_base, ch_max = SCALES[a.scale]
  torch.manual_seed(a.seed)
  G, G_ema, D = build(define_G, define_D, shape, latent, ch_base, ch_max)
  G, G_ema, D = G.to(device), G_ema.to(device), D.to(device)
  A = DiffAugment(policy=['brightness', 'saturation', 'contrast', 'translation',
                          'cutout']).to(device)
  criterion = GANLoss('nsgan').to(device)
  name = torch.cuda.get_device_name(device) if device.type == 'cuda' else 'cpu'
  print(f'the authors\' DUSty-I, torch {torch.__version__} on {name}, {a.scale} scale '
        f'{shape[0]}x{shape[1]}, amp={a.amp}', flush=True)
  result = dict(device=name, torch=torch.__version__, scale=a.scale, shape=shape,
                amp=a.amp, batch=a.batch, threads=torch.get_num_threads())
  if a.train_steps:
    reals = real_batches(torch, a.data_dir, a.batch, a.seed)
    step = train_step_fn(torch, G, G_ema, D, A, criterion, a.batch, latent, shape,
                         device, a.amp, reals)
    train(torch, step, a.train_steps, a.workdir, a.log_every)
    return
  step = train_step_fn(torch, G, G_ema, D, A, criterion, a.batch, latent, shape,
                       device, a.amp)
  med, times = median_time(step, a.repeats, torch, device)
  result['train_step_s'], result['train_step_times'] = med, times
  print(f'  train step, batch {a.batch}, R1 every step: {med:.4f} s (median of '
        f'{a.repeats}; min {min(times):.4f})', flush=True)
  G.eval()
  for b in [int(v) for v in a.invert.split(',') if v]:
    run = invert_fn(torch, G, b, latent, shape, a.invert_iters, device)
    med, times = median_time(run, max(1, a.repeats // 2), torch, device)
    result[f'invert_{b}_s'] = med
    print(f'  inversion, {a.invert_iters} iterations, batch {b}: {med:.3f} s '
          f'({1000 * med / a.invert_iters / b:.2f} ms per scan-iteration)', flush=True)
  if a.out:
    with open(a.out, 'w') as f:
      json.dump(result, f, indent=2)


if __name__ == '__main__':
  main()
