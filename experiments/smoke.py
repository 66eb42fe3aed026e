"""A tiny run for tests and a first look: 16x64 scans, narrow networks."""

from dusty_jax import configs


def get_config():
  c = configs.default()
  c.sensor.preset = ''
  c.sensor.height = 16
  c.sensor.width = 64
  c.data.num_synthetic = 64
  c.latent_dim = 32
  c.ch_base = 8
  c.ch_max = 32
  c.batch_size = 8
  c.r1_every = 2
  c.num_steps = 20
  c.log_every = 5
  c.image_every = 10
  c.checkpoint_every = 10
  c.checkpoint_minutes = 0.0  # by steps only: a slow machine saves what a fast one does
  c.num_images = 4
  return c
