"""Training batches: pure in (seed, step), sliced per process, encoded rows."""

import numpy as np
import pytest

from dusty_jax import codec
from dusty_jax.data.pipeline import Batches

from conftest import random_depth

NUM_SCANS = 23
GLOBAL_BATCH = 8


@pytest.fixture
def depth(tiny):
  # Distinct scans (each its own random pattern of ranges and drops).
  return np.stack([random_depth(tiny, seed=i) for i in range(NUM_SCANS)])


def _row_indices(batch, encoded):
  """Which dataset scan each batch row is, by exact comparison."""
  eq = (batch[:, None] == encoded[None]).all(axis=(2, 3))
  assert (eq.sum(axis=1) == 1).all(), 'a row is not exactly one encoded scan'
  return eq.argmax(axis=1)


def test_same_seed_and_step_give_the_same_batch(depth, tiny):
  a = Batches(depth, tiny, GLOBAL_BATCH, seed=3)
  b = Batches(depth, tiny, GLOBAL_BATCH, seed=3)
  # A fresh iterator (a resumed run) asked out of order agrees.
  later = [b(s) for s in (4, 0, 2)]
  np.testing.assert_array_equal(a(0), later[1])
  np.testing.assert_array_equal(a(2), later[2])
  np.testing.assert_array_equal(a(4), later[0])
  np.testing.assert_array_equal(a(4), a(4))


def test_different_step_or_seed_gives_a_different_batch(depth, tiny):
  encoded = np.asarray(codec.encode(depth, tiny))
  batches = Batches(depth, tiny, GLOBAL_BATCH, seed=3)
  drawn = [tuple(_row_indices(batches(s), encoded)) for s in range(6)]
  assert len(set(drawn)) == len(drawn)
  other = Batches(depth, tiny, GLOBAL_BATCH, seed=4)
  assert tuple(_row_indices(other(0), encoded)) != drawn[0]


def test_rows_are_the_encoded_depth_of_dataset_scans(depth, tiny):
  encoded = np.asarray(codec.encode(depth, tiny))
  batches = Batches(depth, tiny, GLOBAL_BATCH, seed=0)
  seen = set()
  for step in range(20):
    batch = batches(step)
    assert batch.shape == (GLOBAL_BATCH,) + tiny.shape
    assert batch.dtype == np.float32
    seen.update(_row_indices(batch, encoded).tolist())
  # Over 160 draws from 23 scans, every scan shows up (a miss has odds ~1e-3
  # for a uniform draw; the seeds are fixed, so this is deterministic).
  assert seen == set(range(NUM_SCANS))


@pytest.mark.parametrize('process_count', [2, 4])
def test_process_slices_make_up_the_global_batch_in_order(depth, tiny, process_count):
  whole = Batches(depth, tiny, GLOBAL_BATCH, seed=7)
  for step in range(5):
    slices = [Batches(depth, tiny, GLOBAL_BATCH, seed=7, process_index=p,
                      process_count=process_count)(step)
              for p in range(process_count)]
    for s in slices:
      assert s.shape == (GLOBAL_BATCH // process_count,) + tiny.shape
    np.testing.assert_array_equal(np.concatenate(slices), whole(step))


def test_a_batch_that_does_not_split_over_processes_is_refused(depth, tiny):
  with pytest.raises(ValueError, match='batch_size=6 does not split evenly over 4'):
    Batches(depth, tiny, 6, seed=0, process_index=0, process_count=4)
