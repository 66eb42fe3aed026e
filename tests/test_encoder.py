"""The encoder that starts inversion (encoder.py, encoder_trainer.py,
tools/train_encoder.py; its files: generator.py)."""

import json
import os
import re
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dusty_jax
from dusty_jax import (checkpoint, codec, configs, encoder, encoder_trainer, generator, inversion,
                       sampling)
from dusty_jax.codec import ALPHA


@pytest.fixture(scope='module')
def trained(smoke_run, tmp_path_factory):
  """A copy of the smoke run with an encoder trained for a few steps by the
  command line (the shared run is left without one)."""
  from dusty_jax.tools import train_encoder
  run = str(tmp_path_factory.mktemp('enc') / 'run')
  shutil.copytree(smoke_run[1], run)
  train_encoder.main(['--workdir', run, '--steps', '3', '--batch', '4'])
  return run


@pytest.mark.slow
def test_train_command_writes_an_encoder_that_loads_and_resumes(trained, capsys):
  from dusty_jax.tools import train_encoder
  params, _ = dusty_jax.load_checkpoint(trained)
  assert params.encoder is not None
  saved = generator.load_encoder(os.path.join(trained, generator.ENCODER_FILE))[2]
  assert saved['steps'] == 3 and saved['options']['batch'] == 4
  # A rerun with the same flags finds the last checkpoint: nothing to do,
  # and the encoder it writes is the same.
  before = generator.flatten(params.encoder)
  train_encoder.main(['--workdir', trained, '--steps', '3', '--batch', '4'])
  after = generator.flatten(dusty_jax.load_checkpoint(trained)[0].encoder)
  assert before.keys() == after.keys()
  for k in before:
    np.testing.assert_array_equal(before[k], after[k])
  # Every saved option is a flag: the command a shipped model records
  # (study.py --export writes it from these options) reruns as written.
  train_encoder.main(['--workdir', trained] +
                     [f'--{k}={v}' for k, v in saved['options'].items()])
  # Other options than the saved training's are refused, naming the folder.
  with pytest.raises(ValueError, match='other options.*steps'):
    train_encoder.train(trained, encoder_trainer.TrainOptions(steps=5, batch=4))


@pytest.mark.slow
def test_the_encoder_answers_on_the_sphere(trained):
  params, _ = dusty_jax.load_checkpoint(trained)
  scans = sampling.sample(params, jax.random.key(1), 5)['scan']
  z = encoder.encode(params, scans)
  assert z.shape == (5, params.latent_dim)
  np.testing.assert_allclose(np.linalg.norm(np.asarray(z), axis=-1),
                             np.sqrt(params.latent_dim), rtol=1e-5)


@pytest.mark.slow
def test_zero_steps_is_the_encoders_forward_pass(trained):
  params, _ = dusty_jax.load_checkpoint(trained)
  scans = np.array(sampling.sample(params, jax.random.key(2), 3)['scan'])
  scans[0, :4] = np.nan  # NaN counts as a drop, for the encoder too
  out = inversion.invert(params, scans, init='encoder', num_steps=0)
  want_z = encoder.project(jax.jit(encoder.module(params).apply)(
      params.encoder, np.where(np.isfinite(scans), scans, ALPHA)))
  np.testing.assert_allclose(out['latent'], want_z, rtol=1e-5, atol=1e-5)
  raw = jax.jit(params.module().apply)(params.variables, want_z)
  np.testing.assert_allclose(out['inv_depth'], jnp.tanh(raw[..., 0]), atol=1e-5)
  # Refining moves the latent and lowers the fitted loss from there.
  more = inversion.invert(params, scans, init='encoder', num_steps=20)
  assert float(more['loss'].mean()) < float(out['loss'].mean())


def test_corrupt_one_gives_one_of_the_corruptions(kitti):
  rng = np.random.default_rng(0)
  scan = jnp.asarray(rng.uniform(-0.95, -0.85, kitti.shape), jnp.float32)  # 10-40 m: noise keeps them
  opts = encoder_trainer.TrainOptions()
  seen = set()
  for i in range(24):
    x = np.asarray(encoder_trainer.corrupt_one(jax.random.key(i), scan, kitti, opts))
    dropped = x == ALPHA
    rows_only = dropped.any(axis=1) & ~dropped.all(axis=1)
    if not dropped.any():
      assert np.abs(x - scan).max() < 0.5  # as is, or noise that kept every point
      seen.add('none or noise')
    elif dropped.all(axis=1).any() and not rows_only.any():
      kept = np.flatnonzero(~dropped.all(axis=1))
      assert np.all(np.diff(kept) == kept[1] - kept[0]) and kept[0] == 0
      np.testing.assert_array_equal(x[kept], np.asarray(scan)[kept])
      seen.add('beams')
    else:
      assert 0.45 < dropped.mean() < 0.97
      np.testing.assert_array_equal(x[~dropped], np.asarray(scan)[~dropped])
      seen.add('drop')
  assert seen == {'none or noise', 'beams', 'drop'}


@pytest.mark.slow
def test_loss_terms_match_their_definition(trained):
  params, _ = dusty_jax.load_checkpoint(trained)
  opts = encoder_trainer.TrainOptions(w_latent=2.0, w_rec=0.5)
  z, inputs, target = jax.jit(encoder_trainer.samples, static_argnums=(2, 3))(
      params, jax.random.key(3), 4, opts)
  loss_fn = jax.jit(encoder_trainer.loss_fn, static_argnames=('opts',))
  total, (lat, rec, real) = loss_fn(params.encoder, params, z, inputs, target, opts=opts)
  apply = jax.jit(params.module().apply)
  e = np.asarray(encoder.encode(params, inputs), np.float64)
  zz = np.asarray(z, np.float64)
  d = params.latent_dim
  # On the sphere, |e - z|^2 / d = 2 (1 - cos(e, z)).
  cos = (e * zz).sum(-1) / d
  np.testing.assert_allclose(float(lat), np.mean(2 * (1 - cos)), rtol=1e-4)
  x = np.tanh(np.asarray(apply(params.variables, e.astype(np.float32)))[..., 0])
  np.testing.assert_allclose(float(rec), np.abs(x - np.asarray(target)).mean(), rtol=1e-4)
  np.testing.assert_allclose(float(total), 2.0 * float(lat) + 0.5 * float(rec), rtol=1e-6)
  assert float(real) == 0.0  # no real scans given
  # The real-scan term is the inversion's objective, scan by scan.
  x = jnp.tanh(apply(params.variables, encoder.encode(params, inputs))[..., 0])
  want = np.mean([float(inversion.objective(x[i], target[i], target[i] > ALPHA))
                  for i in range(len(x))])
  _, (_, _, got) = loss_fn(params.encoder, params, z, inputs, target, opts=opts,
                           real_inputs=inputs, real=target)
  np.testing.assert_allclose(float(got), want, rtol=1e-5)


@pytest.mark.slow
def test_export_round_trip_and_format_1_files_still_load(trained, tmp_path):
  """Format 2 round trip; format 1 (no encoder) loads; a file from before
  format 1 (flat fields, the research era's) is one line naming the last
  version that reads it."""
  params, _ = dusty_jax.load_checkpoint(trained)
  path = generator.export(params, str(tmp_path / 'g.npz'))
  back = generator.load_file(path)
  assert back.encoder_settings == params.encoder_settings
  for (ka, va), (kb, vb) in zip(generator.flatten(params.encoder).items(),
                                generator.flatten(back.encoder).items()):
    assert ka == kb
    np.testing.assert_array_equal(va, vb)
  # A format-1 file (no encoder arrays) loads, without an encoder.
  with np.load(path) as f:
    arrs = {k: f[k] for k in f.files if not k.startswith('encoder/')}
  meta = json.loads(str(arrs.pop('meta')))
  meta['format'] = 1
  meta.pop('encoder')
  np.savez(tmp_path / 'old.npz', meta=np.asarray(json.dumps(meta)), **arrs)
  old = generator.load_file(str(tmp_path / 'old.npz'))
  assert old.encoder is None
  flat = dict({k: v for k, v in meta.items() if k not in ('settings', 'format')},
              **meta['settings'])
  np.savez(tmp_path / 'older.npz', meta=np.asarray(json.dumps(flat)), **arrs)
  with pytest.raises(configs.ConfigError, match=(
      r'older\.npz: no model settings; written by a research-era dusty_jax; dusty_jax '
      r'0\.1\.0 is the last version that reads it$')):
    generator.load_file(str(tmp_path / 'older.npz'))
  np.testing.assert_array_equal(old.angles, back.angles)


@pytest.mark.slow
def test_a_second_encoder_training_on_one_folder_is_refused(trained):
  """Two encoder trainings on one run would write each other's checkpoints:
  the second is refused, naming the holder, and the folder is left as it was."""
  from dusty_jax import parallel
  folder = os.path.join(trained, encoder_trainer.DIRECTORY)
  before = sorted(os.listdir(folder))
  params, _ = dusty_jax.load_checkpoint(trained)
  with parallel.hold_workdir(folder):
    with pytest.raises(parallel.WorkdirInUse,
                       match=f'{re.escape(folder)} is in use.*pid {os.getpid()}'):
      encoder_trainer.train(params, folder, encoder_trainer.TrainOptions(steps=3, batch=4, w_real=0))
  assert sorted(os.listdir(folder)) == before


@pytest.mark.slow
def test_a_resumed_encoder_training_clears_a_save_cut_short(trained):
  """A save cut short (a kill) leaves orbax's tmp folder; the next training
  on the run, which holds the folder alone, removes it and resumes."""
  from dusty_jax.tools import train_encoder
  folder = os.path.join(trained, encoder_trainer.DIRECTORY, checkpoint.DIRECTORY)
  assert os.path.isdir(os.path.join(folder, '3'))
  cut = os.path.join(folder, '6.orbax-checkpoint-tmp-1')
  os.makedirs(cut)
  train_encoder.main(['--workdir', trained, '--steps', '3', '--batch', '4'])
  assert sorted(os.listdir(folder)) == ['3']


@pytest.mark.slow
def test_bad_inputs_get_clear_errors(smoke_run, trained, tmp_path):
  plain, _ = dusty_jax.load_checkpoint(smoke_run[1])
  scan = np.asarray(sampling.sample(plain, jax.random.key(0), 1)['scan'][0])
  with pytest.raises(ValueError, match='no encoder.*train_encoder --workdir'):
    inversion.invert(plain, scan, init='encoder', num_steps=0)
  params, _ = dusty_jax.load_checkpoint(trained)
  with pytest.raises(ValueError, match=r'scan of shape \(8, 64\)'):
    inversion.invert(params, scan[:8], init='encoder', num_steps=0)
  with pytest.raises(ValueError, match='whole number >= 0'):
    inversion.invert(params, scan, init='encoder', num_steps=-1)
  # An encoder of another generator's size is refused when its run loads.
  run = str(tmp_path / 'run')
  shutil.copytree(trained, run)
  enc, settings, meta = generator.load_encoder(os.path.join(run, generator.ENCODER_FILE))
  generator.save_encoder(os.path.join(run, generator.ENCODER_FILE), enc,
               encoder.EncoderSettings(hidden=settings.hidden + 1), meta)
  with pytest.raises(ValueError, match='encoder does not fit'):
    dusty_jax.load_checkpoint(run)
  from dusty_jax.tools import train_encoder
  with pytest.raises(FileNotFoundError, match='nothing: no such run directory$'):
    train_encoder.train(str(tmp_path / 'nothing'), encoder_trainer.TrainOptions())
  for model in ('sim-dusty2', os.path.join(run, generator.ENCODER_FILE)):  # no training state
    with pytest.raises(FileNotFoundError, match='not a training run directory .*pretrained'):
      train_encoder.train(model, encoder_trainer.TrainOptions())


def test_shipped_encoder_beats_a_random_start():
  """On a held-out simulated scan (scene seed 7; the study trained on seed
  0), 10 iterations from the shipped sim-dusty1's encoder fit the returned
  points with at most 0.9x the error of 10 from a random start (0.81x
  when exported)."""
  from dusty_jax.data import synthetic
  params = dusty_jax.load_pretrained('sim-dusty1')
  assert params.encoder is not None, 'sim-dusty1 ships an encoder'
  obs, _, _ = synthetic.simulate(2, params.sensor, seed=7, progress=False)
  scan = np.asarray(codec.encode(obs, params.sensor))
  enc = inversion.invert(params, scan, init='encoder', num_steps=10)
  rnd = inversion.invert(params, scan, init='random', num_steps=10)
  assert float(enc['loss'].mean()) < 0.9 * float(rnd['loss'].mean()), (
      enc['loss'], rnd['loss'])
