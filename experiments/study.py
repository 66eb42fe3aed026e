"""The study (benchmarks/study.py): a model trained on simulated HDL-64E
scans with a point-drop preset, at the CPU scale or the paper's.

    --config experiments/study.py:MODEL,PRESET,SCALE

MODEL: baseline | dusty1 | dusty2 (default dusty1); PRESET: a name of
PRESETS: authors (the paper's training, default), levels (the same, drop
levels fitted after it: sim-dusty1's), dips (sim-dusty2's); SCALE: cpu
(default) | paper. Parts left out or empty take their default: `:dusty2` is
DUSty-II, authors, cpu; `:dusty1,levels,paper` the shipped DUSty-I's recipe
at the paper's size. experiments/synthetic.py and synthetic_gpu.py build on
:func:`study`.
"""

from dusty_jax import configs, models

# The drops options (dusty_jax/drops.py) the shipped models trained with:
# 'authors' is the paper's training (sim-baseline, sim-dusty1-authors);
# 'levels' the same with drop levels fitted after it (sim-dusty1); 'dips'
# trained sim-dusty2, its levels fitted after training too
# (benchmarks/research/drops/lineage.py: how they were reached).
LEVELS = dict(depth_levels=True)
DIPS = dict(mask_bias=1.386, ring_bias=True, rate_weight=100.0, rate_head_only=True,
            mask_detached=True, dip_weight=10.0, depth_levels=True)
PRESETS = {'authors': {}, 'levels': LEVELS, 'dips': DIPS}
# 'cpu' fits the three trainings in about 100 minutes on 2 CPU cores;
# 'paper' is the paper's size and schedule (the defaults).
SCALES = ('cpu', 'paper')
DEFAULTS = ('dusty1', 'authors', 'cpu')  # MODEL, PRESET, SCALE


def study(model: str = 'dusty1', preset: str = 'authors', scale: str = 'cpu'):
  """``model`` trained on simulated HDL-64E scans with the drops options
  ``preset`` (PRESETS) at ``scale`` (SCALES)."""
  for what, name, known in (('model', model, models.VARIANTS),
                            ('preset', preset, PRESETS), ('scale', scale, SCALES)):
    if name not in known:
      raise configs.ConfigError(f'unknown study {what} {name!r}; known: {", ".join(known)}')
  c = configs.default()
  c.model = model
  c.drops.update(PRESETS[preset])
  c.sensor.preset = 'kitti'
  c.data.dir = ''
  c.data.num_synthetic = 2000
  if scale == 'cpu':
    c.latent_dim = 128
    c.ch_base = 16
    c.ch_max = 128
    c.batch_size = 16
    c.ema_rampup = 0.05
    c.num_steps = 2500
    c.log_every = 50
    c.image_every = 500
    c.checkpoint_every = 250
  return c


def get_config(arg: str = ''):
  parts = [p.strip() for p in arg.split(',')] if arg else []
  if len(parts) > len(DEFAULTS):
    raise configs.ConfigError(f'experiments/study.py:{arg}: give at most MODEL,PRESET,SCALE '
                              '(e.g. dusty1,levels,cpu)')
  return study(*(p or d for p, d in zip(parts + [''] * 3, DEFAULTS)))
