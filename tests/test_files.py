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
