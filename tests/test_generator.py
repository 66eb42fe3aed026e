"""A trained generator on its own: loading a run without the trainer, the
discriminator, the optimisers or the data; the public names."""

import importlib
import inspect
import json
import os
import pkgutil
import shutil
import subprocess
import sys

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

import dusty_jax
from dusty_jax import checkpoint, configs, generator, models, trainer

HERE = os.path.dirname(os.path.abspath(__file__))


def _snapshot(*roots):
  """{path: (size, mtime_ns)} of every file and directory under ``roots``."""
  out = {}
  for root in roots:
    for d, dirs, files in os.walk(root):
      for name in dirs + files:
        p = os.path.join(d, name)
        st = os.stat(p)
        out[p] = (st.st_size if name in files else None, st.st_mtime_ns)
  return out


def test_copied_run_loads_without_trainer_or_data(smoke_run, tmp_path):
  """A run directory copied elsewhere, with an empty data cache and no
  dataset, loads in a fresh process that never imports the trainer, the
  data pipeline or the simulator, and writes nothing."""
  config, workdir, state = smoke_run
  copy = tmp_path / 'copied_run'
  shutil.copytree(workdir, copy)
  cache = tmp_path / 'empty_cache'
  cache.mkdir()
  before = _snapshot(copy, cache)
  code = (
      'import sys, json, numpy as np, jax, dusty_jax\n'
      f'params, config = dusty_jax.load_checkpoint({str(copy)!r})\n'
      'leaves = [np.asarray(x).ravel()[:3].tolist() for x in jax.tree.leaves(params.variables)]\n'
      'print(json.dumps({"modules": sorted(m for m in sys.modules if m.startswith("dusty_jax")),\n'
      '                  "leaves": leaves, "model": params.model,\n'
      '                  "angles": np.asarray(params.angles).shape}))\n')
  env = dict(os.environ, DUSTY_JAX_CACHE=str(cache), HOME=str(tmp_path / 'home'))
  res = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                       text=True, timeout=600, cwd=str(tmp_path))
  assert res.returncode == 0, res.stderr[-2000:]
  out = json.loads(res.stdout.strip().splitlines()[-1])
  for banned in ('dusty_jax.trainer', 'dusty_jax.data.pipeline', 'dusty_jax.data.synthetic',
                 'dusty_jax.augment', 'dusty_jax.losses'):
    assert banned not in out['modules']
  assert out['model'] == 'dusty1' and out['angles'] == [2, 16, 64]
  want = [np.asarray(x).ravel()[:3].tolist() for x in jax.tree.leaves(state.ema_params)]
  assert out['leaves'] == want
  assert _snapshot(copy, cache) == before
  assert not (tmp_path / 'home').exists()


@pytest.mark.slow
def test_load_equals_the_trainer_state(smoke_run):
  """The generator read alone equals the one in the full train state, for
  the EMA and the raw generator, at the latest and an earlier step."""
  config, workdir, _ = smoke_run
  setup = trainer.make_setup(config, generator.read_spec(workdir)[0])
  target = trainer.init_state(setup, jax.random.key(0))
  mngr = checkpoint.manager(workdir)
  for step in (2, 4):
    full = mngr.restore(step, args=ocp.args.StandardRestore(
        jax.tree.map(ocp.utils.to_shape_dtype_struct, target)))  # orbax itself
    for ema, want in ((True, full.ema_params), (False, full.g_params)):
      params, _ = dusty_jax.load_checkpoint(workdir, step=step, ema=ema)
      for a, b in zip(jax.tree.leaves(params.variables), jax.tree.leaves(want)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  assert params.settings == configs.model_settings(config)
  assert params.tolerance == config.tolerance


@pytest.mark.slow
def test_run_from_before_generator_json(smoke_run, tmp_path):
  """Runs written before generator.json are described by config.json; a run
  without its angle table says how to give one instead of guessing."""
  config, workdir, _ = smoke_run
  copy = tmp_path / 'old_run'
  shutil.copytree(workdir, copy)
  new, _ = dusty_jax.load_checkpoint(str(copy))
  os.remove(copy / generator.SPEC_FILE)
  old, _ = dusty_jax.load_checkpoint(str(copy))
  assert (old.settings, old.sensor, old.tolerance) == (new.settings, new.sensor,
                                                      new.tolerance)
  os.remove(copy / 'angles.npy')
  with pytest.raises(FileNotFoundError, match="angles.npy.*angles='nominal'"):
    dusty_jax.load_checkpoint(str(copy))
  nominal, _ = dusty_jax.load_checkpoint(str(copy), angles='nominal')
  np.testing.assert_array_equal(np.asarray(nominal.angles), new.sensor.nominal_angles())
  generator.set_tolerance(str(copy), 0.01)  # gives the old run a generator.json
  assert (copy / generator.SPEC_FILE).is_file()
  tuned, _ = dusty_jax.load_checkpoint(str(copy), angles='nominal')
  assert (tuned.settings, tuned.tolerance) == (new.settings, 0.01)


def test_exported_file_loads_like_the_run(smoke_run, tmp_path):
  _, workdir, _ = smoke_run
  params, _ = dusty_jax.load_checkpoint(workdir)
  path = generator.export(params, str(tmp_path / 'g.npz'), source='test')
  back, config = dusty_jax.load_checkpoint(path)
  assert config is None
  assert (back.settings, back.sensor, back.tolerance) == (params.settings, params.sensor,
                                                         params.tolerance)
  z = jax.random.normal(jax.random.key(1), (2, params.latent_dim))
  generate = jax.jit(dusty_jax.generate)  # one compilation: same static fields
  a, b = (generate(p, z, jax.random.key(2)) for p in (params, back))
  np.testing.assert_array_equal(np.asarray(a['scan']), np.asarray(b['scan']))


@pytest.mark.slow
def test_tolerance_survives_resume(smoke_run, tmp_path):
  """A tuned beta recorded in the run is what loading decodes with, and a
  resumed training keeps it."""
  config, workdir, _ = smoke_run
  copy = tmp_path / 'tuned'
  shutil.copytree(workdir, copy)
  generator.set_tolerance(str(copy), 0.0321)
  assert dusty_jax.load_checkpoint(str(copy))[0].tolerance == 0.0321
  longer = config.copy_and_resolve_references()
  longer.num_steps = 5
  trainer.train_and_evaluate(longer, str(copy), log=lambda m: None)
  params, _ = dusty_jax.load_checkpoint(str(copy))
  assert params.tolerance == 0.0321
  assert sorted(checkpoint.manager(str(copy)).all_steps())[-1] == 5


def test_variables_that_do_not_fit_are_refused(smoke_run, tmp_path):
  config, workdir, _ = smoke_run
  copy = tmp_path / 'mismatch'
  shutil.copytree(workdir, copy)
  spec = json.load(open(copy / generator.SPEC_FILE))
  spec['settings']['ch_max'] = 64
  json.dump(spec, open(copy / generator.SPEC_FILE, 'w'))
  with pytest.raises(ValueError, match='do not fit the described network'):
    dusty_jax.load_checkpoint(str(copy))
  (copy / generator.SPEC_FILE).write_text('{"sensor": ')
  with pytest.raises(ValueError, match='generator.json: not valid JSON'):
    dusty_jax.load_checkpoint(str(copy))


def test_model_settings_is_one_frozen_value(tiny):
  from train_helpers import tiny_config
  c = tiny_config(model='dusty2', eqlr='fan_in', tau=0.5)
  s = configs.model_settings(c)
  assert s == models.ModelSettings('dusty2', c.latent_dim, c.ch_base, c.ch_max,
                                   'fan_in', 0.5)
  with pytest.raises(Exception):  # frozen
    s.model = 'baseline'
  for bad, msg in [(dict(model='dusty3'), 'unknown model'), (dict(eqlr='x'), 'unknown eqlr'),
                   (dict(latent_dim=0), 'latent_dim=0'), (dict(tau=0.0), 'tau=0.0')]:
    with pytest.raises(ValueError, match=msg):
      models.ModelSettings(**bad)
  g = s.generator(tiny)
  assert (g.out_channels, g.latent_dim, g.eqlr) == (3, c.latent_dim, 'fan_in')


# The public API and the functions it must name (README, __init__ docstring).
PUBLIC = {
    'invert': 'dusty_jax.inversion.invert',
    'render_drops': 'dusty_jax.inversion.render_drops',
    'generate': 'dusty_jax.sampling.generate',
    'sample': 'dusty_jax.sampling.sample',
    'load_checkpoint': 'dusty_jax.generator.load',
    'load_pretrained': 'dusty_jax.pretrained.load_pretrained',
    'get_sensor': 'dusty_jax.sensor.get_sensor',
}


def test_public_names_survive_importing_every_submodule():
  """No submodule shadows a public name: after importing all of them (the
  command-line tools included) each public name is still its function, with
  its own signature and docstring."""
  names = []
  for m in pkgutil.walk_packages(dusty_jax.__path__, 'dusty_jax.'):
    importlib.import_module(m.name)
    names.append(m.name)
  assert 'dusty_jax.tools.invert' in names and 'dusty_jax.invert' not in names
  top = {n.split('.')[1] for n in names}
  assert not top & set(dusty_jax.__all__), top & set(dusty_jax.__all__)
  assert set(PUBLIC) <= set(dusty_jax.__all__)
  for name, path in PUBLIC.items():
    module, attr = path.rsplit('.', 1)
    fn = getattr(dusty_jax, name)
    assert inspect.isfunction(fn), (name, type(fn))
    assert fn is getattr(sys.modules[module], attr), name
    assert 'args' not in inspect.signature(fn).parameters, name
    assert fn.__doc__ and 'python -m' not in fn.__doc__, name
  assert inspect.isclass(dusty_jax.GeneratorParams)


@pytest.mark.slow
def test_generator_files_alone_and_what_is_refused(smoke_run, tmp_path):
  """generator.json + angles.npy + checkpoints/ are enough (config None); a
  newer format, an unknown item, and tools given the wrong kind of file fail
  with a message, before any work."""
  from dusty_jax.tools import convert, evaluate
  _, workdir, _ = smoke_run
  bare = tmp_path / 'bare'
  bare.mkdir()
  for name in (generator.SPEC_FILE, 'angles.npy', 'checkpoints'):
    src = os.path.join(workdir, name)
    (shutil.copytree if os.path.isdir(src) else shutil.copy)(src, bare / name)
  params, config = dusty_jax.load_checkpoint(str(bare))
  full, _ = dusty_jax.load_checkpoint(workdir)
  assert config is None and params.settings == full.settings
  with pytest.raises(KeyError, match="holds no 'emma_params'"):
    checkpoint.restore_item(str(bare / 'checkpoints'), 'emma_params')
  spec = json.load(open(bare / generator.SPEC_FILE))
  json.dump(dict(spec, format=generator.FORMAT + 1), open(bare / generator.SPEC_FILE, 'w'))
  with pytest.raises(ValueError, match='newer dusty_jax'):
    dusty_jax.load_checkpoint(str(bare))
  npz = generator.export(full, str(tmp_path / 'g.npz'))
  with pytest.raises(SystemExit, match='a dusty_jax generator file'):
    convert.main(['--pth', npz, '--workdir', str(tmp_path / 'converted')])
  assert not (tmp_path / 'converted').exists()
  # A generator file names no dataset: evaluate asks for one (--data_dir).
  with pytest.raises(SystemExit, match='no config.json naming a dataset.*give --data_dir'):
    evaluate.main(['--workdir', npz])
  # So does invert --split; with --data_dir it evaluates that dataset's split.
  from dusty_jax.data import pipeline
  from dusty_jax.tools import invert
  with pytest.raises(SystemExit, match='no config.json naming a dataset for --split; give '
                     '--data_dir'):
    invert.main(['--workdir', npz, '--split', 'val'])
  data = pipeline.dataset_dir(smoke_run[0], full.sensor, log=lambda m: None)
  out = tmp_path / 'inverted'
  invert.main(['--workdir', npz, '--split', 'val', '--num', '2', '--steps', '1',
               '--data_dir', data, '--out', str(out)])
  assert json.load(open(out / 'metrics.json'))['num'] == 2
