"""files.atomic_write: the new file whole, or the old one untouched."""

import json
import os

import numpy as np
import pytest

from dusty_jax import files


def test_the_file_is_written_whole_and_replaces_the_old_one(tmp_path):
  path = str(tmp_path / 'a.json')
  with files.atomic_write(path) as f:
    json.dump({'x': 1}, f)
    assert not os.path.exists(path)  # nothing at the path until the write is done
  assert json.load(open(path)) == {'x': 1}
  with files.atomic_write(path) as f:
    f.write('{"x": 2}')
  assert json.load(open(path)) == {'x': 2}
  assert os.listdir(tmp_path) == ['a.json']  # no temporary file left


def test_binary_files_take_numpy_writers(tmp_path):
  path = str(tmp_path / 'b.npz')
  with files.atomic_write(path, 'wb') as f:
    np.savez_compressed(f, a=np.arange(5.0))
  np.testing.assert_array_equal(np.load(path)['a'], np.arange(5.0))
  assert os.listdir(tmp_path) == ['b.npz']  # not b.npz.tmp.npz


@pytest.mark.parametrize('error', [ValueError('half-way'), KeyboardInterrupt()])
def test_a_write_that_fails_leaves_the_old_file_and_no_temporary(tmp_path, error):
  path = tmp_path / 'c.txt'
  path.write_text('old')
  with pytest.raises(type(error)):
    with files.atomic_write(str(path)) as f:
      f.write('new, cut short')
      f.flush()
      raise error
  assert path.read_text() == 'old'
  assert os.listdir(tmp_path) == ['c.txt']


def test_a_missing_folder_or_a_bad_mode_is_refused(tmp_path):
  with pytest.raises(FileNotFoundError):
    with files.atomic_write(str(tmp_path / 'nowhere' / 'd.txt')) as f:
      f.write('x')
  with pytest.raises(ValueError, match=r"mode='a': atomic_write writes a whole file"):
    with files.atomic_write(str(tmp_path / 'e.txt'), 'a'):
      pass
  assert os.listdir(tmp_path) == []


def test_two_writers_of_one_file_at_once_each_move_theirs_whole(tmp_path):
  """As the processes of a multi-process training write one dataset's
  meta.json: each has its own temporary, the last to finish wins whole."""
  path = str(tmp_path / 'meta.json')
  with files.atomic_write(path) as first:
    with files.atomic_write(path) as second:
      first.write('{"by": "first"}')
      second.write('{"by": "second", "longer": true}')
    assert json.load(open(path)) == {'by': 'second', 'longer': True}
  assert json.load(open(path)) == {'by': 'first'}
  assert os.listdir(tmp_path) == ['meta.json']


def test_a_path_for_writers_that_take_one(tmp_path):
  path = str(tmp_path / 'x.npy')
  with files.atomic_path(path, '.npy') as tmp:
    assert tmp.endswith('.npy') and os.path.dirname(tmp) == str(tmp_path)
    np.lib.format.open_memmap(tmp, mode='w+', dtype=np.float32, shape=(3,))[:] = [1, 2, 3]
    assert not os.path.exists(path)
  np.testing.assert_array_equal(np.load(path), [1, 2, 3])
  with pytest.raises(KeyboardInterrupt):
    with files.atomic_path(path, '.npy') as tmp:
      np.save(tmp, np.zeros(2))
      raise KeyboardInterrupt
  np.testing.assert_array_equal(np.load(path), [1, 2, 3])  # the old file stays
  assert os.listdir(tmp_path) == ['x.npy']
