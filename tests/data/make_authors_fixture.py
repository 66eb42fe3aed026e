"""Writes tests/data/authors_*: tiny checkpoints saved by real torch.save in
the authors' layout (kazuto1011/dusty-gan), their configs, and their
generators' outputs for fixed latents.

    python tests/data/make_authors_fixture.py /path/to/dusty-gan

Needs torch and omegaconf, and the authors' repository (not part of this
project; nothing of it is copied here: their modules are imported at run
time from the path given). The test suite needs neither.
"""

import os
import sys

import numpy as np
import torch
import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
SHAPE = [32, 64]
GEN = {'baseline': ('none/dcgan_eqlr', {'depth': 1}),
       'dusty1': ('dusty1/dcgan_eqlr', {'depth': 1, 'confidence': 1}),
       'dusty2': ('dusty2/dcgan_eqlr', {'depth': 1, 'confidence': 2})}


def main(repo):
  sys.path.insert(0, repo)
  from omegaconf import OmegaConf
  from models import define_D, define_G
  torch.manual_seed(0)
  for name, (arch, out_ch) in GEN.items():
    y = {'dataset': {'name': 'tiny', 'shape': SHAPE, 'min_depth': 0.9, 'max_depth': 120.0},
         'model': {'gen': {'arch': arch, 'in_ch': 8, 'out_ch': out_ch, 'ch_base': 4,
                           'ch_max': 8, 'drop_const': -1, 'shape': SHAPE, 'tau': 1},
                   'dis': {'arch': 'dcgan_eqlr', 'in_ch': 1, 'ch_base': 4, 'ch_max': 8,
                           'shape': SHAPE},
                   'ring': True}}
    cfg = OmegaConf.create(y)
    G, D, G_ema = define_G(cfg), define_D(cfg), define_G(cfg)
    # Distinct EMA weights, so that loading G instead of G_ema would show.
    with torch.no_grad():
      for p in G_ema.parameters():
        p.add_(0.1 * torch.randn_like(p))
    oG = torch.optim.Adam(G.parameters(), lr=0.002, betas=(0.0, 0.99))
    oD = torch.optim.Adam(D.parameters(), lr=0.002, betas=(0.0, 0.99))
    # One update, so the optimiser states hold tensors as in a real run.
    D(G(latent=torch.randn(2, 8))['depth']).mean().backward()
    oG.step()
    oD.step()
    torch.save({'step': 1234, 'G': G.state_dict(), 'D': D.state_dict(),
                'G_ema': G_ema.state_dict(), 'optim_G': oG.state_dict(),
                'optim_D': oD.state_dict()},
               os.path.join(HERE, f'authors_{name}.pth'))
    with open(os.path.join(HERE, f'authors_{name}_config.yaml'), 'w') as f:
      yaml.safe_dump(y, f)
    z = torch.randn(3, 8)
    G_ema.eval()
    with torch.no_grad():
      out = G_ema(latent=z) if name == 'baseline' else G_ema.backbone(z)
    arrays = {'z': z.numpy(), 'depth_orig': out['depth'][:, 0].numpy()}
    if name != 'baseline':
      arrays['confidence'] = out['confidence'].permute(0, 2, 3, 1).numpy()
    np.savez(os.path.join(HERE, f'authors_{name}_outputs.npz'), **arrays)
    print(name, {k: v.shape for k, v in arrays.items()})
  write_angles()


def write_angles():
  """An angles.pt as their process_kitti.py writes it (pitch, yaw at a
  finer native width), and the table their LiDAR class makes of it for the
  fixture's shape (F.interpolate, bilinear, as in utils/lidar.py)."""
  g = torch.Generator().manual_seed(1)
  h, w = 16, 128
  pitch = torch.linspace(0.03, -0.4, h)[:, None].expand(h, w)
  yaw = torch.linspace(3.1, -3.1, w)[None, :].expand(h, w)
  angles = torch.stack([pitch, yaw]) + 0.01 * torch.randn(2, h, w, generator=g)
  torch.save(angles, os.path.join(HERE, 'authors_angles.pt'))
  table = torch.nn.functional.interpolate(angles[None], size=SHAPE, mode='bilinear')[0]
  np.save(os.path.join(HERE, 'authors_angles_resized.npy'), table.numpy())
  print('angles', tuple(angles.shape), '->', tuple(table.shape))


if __name__ == '__main__':
  main(sys.argv[1])
