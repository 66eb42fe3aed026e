"""checkpoint.py alone: how a failed save reads, and quiet's filters."""

import json
import logging
import os
import re
import shutil

import numpy as np
import pytest

from dusty_jax import checkpoint


def test_a_failed_save_names_its_step_and_a_full_disk_by_the_room_left(tmp_path,
                                                                      monkeypatch):
  """TensorStore reports a full disk as a ValueError whose words are not
  read: a failed save is 'no space left' when the disk is then left with
  less room than a step, and names the step whose save failed in the
  background (tracked by orbax, not on disk), not the one being started."""
  state = {'w': np.ones((64, 64), np.float32)}
  mngr = checkpoint.manager(str(tmp_path / 'run'))
  folder = tmp_path / 'run' / 'checkpoints'
  for step in (1, 2):
    checkpoint.save(mngr, step, state)
    mngr.wait_until_finished()
  os.replace(folder / '2', tmp_path / 'cut')  # as a commit that failed leaves it

  def fails():
    raise ValueError('a write failed')

  monkeypatch.setattr(mngr, 'wait_until_finished', fails)
  usage = shutil.disk_usage(folder)
  for free, want in (
      (0, f'no space left on device while writing checkpoint 2 in {folder}; step 1 is '
          'intact; free space and rerun to resume from 1'),
      (usage.free, f'writing checkpoint 2 in {folder} failed (ValueError: a write failed); '
                   'step 1 is intact; rerun to resume from 1')):
    monkeypatch.setattr(shutil, 'disk_usage', lambda path: usage._replace(free=free))
    with pytest.raises(checkpoint.CheckpointError, match=f'^{re.escape(want)}$'):
      checkpoint.save(mngr, 3, state)  # the failure of 2 surfaces here
  assert sorted(os.listdir(folder)) == ['1']
  assert checkpoint._read_sizes(str(folder)).keys() == {'1'}  # beside, for step 1


def test_quiet_nests_and_drops_only_orbax_records():
  absl = logging.getLogger('absl')
  record = lambda path: logging.LogRecord('absl', logging.WARNING, path, 1, 'm', (), None)
  orbax = record(os.path.join(checkpoint._ORBAX, 'checkpoint_manager.py'))
  ours = record(os.path.abspath(__file__))
  with checkpoint.quiet():
    with checkpoint.quiet():
      assert not absl.filter(orbax) and absl.filter(ours)
    assert not absl.filter(orbax)  # the inner exit left the outer's filter
  assert absl.filter(orbax)


def test_a_truncated_step_without_a_size_record_falls_back_by_type(tmp_path):
  """A step the size record does not vouch for (a run's steps from before
  the record, or from a process that died) is read; orbax's partial read of
  a truncated array raises a bare Exception, which still falls back."""
  state = {'ema': {'w': np.arange(4096, dtype=np.float32)}, 'opt': np.zeros(3, np.float32)}
  mngr = checkpoint.manager(str(tmp_path / 'run'))
  for step in (1, 2):
    checkpoint.save(mngr, step, {**state, 'ema': {'w': state['ema']['w'] + step}})
    checkpoint.wait(mngr)
  folder = tmp_path / 'run' / 'checkpoints'
  os.remove(str(folder) + checkpoint.SIZES)
  for path in (folder / '2').rglob('*'):
    if path.is_file() and path.stat().st_size > 1024:  # the arrays' data files
      path.write_bytes(path.read_bytes()[:path.stat().st_size // 3])
  lines = []
  item, step = checkpoint.restore_item(str(folder), 'ema', log=lines.append)
  assert step == 1 and np.array_equal(item['w'], state['ema']['w'] + 1)
  assert lines[0].startswith(f'warning: checkpoint step 2 in {folder} does not restore '
                             '(unreadable: ')
  with pytest.raises(checkpoint.CheckpointError, match='checkpoint step 2 does not restore'):
    checkpoint.restore_item(str(folder), 'ema', step=2, log=lines.append)


def test_steps_found_when_a_run_opens_are_read_unchecked(tmp_path):
  """Sizes are noted for the steps a run saves, not for those it found on
  opening (an earlier process may have died damaging them)."""
  state = {'w': np.ones(64, np.float32)}
  mngr = checkpoint.manager(str(tmp_path / 'run'))
  checkpoint.save(mngr, 1, state)
  checkpoint.wait(mngr)
  sizes = str(tmp_path / 'run' / 'checkpoints') + checkpoint.SIZES
  os.remove(sizes)
  mngr = checkpoint.manager(str(tmp_path / 'run'))
  checkpoint.save(mngr, 2, state)
  checkpoint.wait(mngr)
  with open(sizes) as f:
    record = json.load(f)
  assert record['1'] is None and record['2']
