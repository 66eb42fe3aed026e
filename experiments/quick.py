"""DUSty-I on the simulated HDL-64E scans with a narrower network: visible
learning within minutes on a CPU (the paper-size model is synthetic.py)."""

from dusty_jax import configs


def get_config():
  c = configs.default()
  c.sensor.preset = 'kitti'
  c.latent_dim = 128
  c.ch_base = 16
  c.ch_max = 128
  c.batch_size = 16
  c.ema_rampup = 0.05  # short runs: let the EMA follow the generator early
  c.num_steps = 3000
  c.log_every = 20
  c.image_every = 100
  c.checkpoint_every = 200
  return c
