"""MetricWriter: metrics.jsonl and the TensorBoard event file hold what was written."""

import errno
import json
import os

import numpy as np
import pytest

from dusty_jax import writers
from event_files import read_events, scalars


def _event_files(workdir):
  return [os.path.join(workdir, f) for f in os.listdir(workdir)
          if f.startswith('events.out.tfevents.')]


def test_event_file_holds_each_scalar_at_its_step(tmp_path):
  w = writers.MetricWriter(str(tmp_path))
  w.write(2, {'loss_d': 1.25, 'loss_g': np.float32(-0.5)})
  w.write(4, {'loss_d': 0.75, 'images_per_sec': 1234.5})
  w.close()
  (path,) = _event_files(tmp_path)
  events = read_events(path)
  assert events[0].file_version == 'brain.Event:2'
  assert scalars(events) == [(2, 'loss_d', 1.25), (2, 'loss_g', -0.5),
                             (4, 'loss_d', 0.75), (4, 'images_per_sec', 1234.5)]
  # Event and JSONL record of a step carry the same wall time.
  recs = [json.loads(l) for l in open(tmp_path / 'metrics.jsonl')]
  times = {e.step: e.wall_time for e in events[1:]}
  assert [r['step'] for r in recs] == [2, 4]
  assert all(times[r['step']] == r['time'] for r in recs)


def test_disabled_writer_writes_nothing(tmp_path):
  w = writers.MetricWriter(str(tmp_path / 'w'), enabled=False)
  w.write(1, {'loss': 1.0})
  w.close()
  assert not (tmp_path / 'w').exists()


def test_metrics_jsonl_has_one_record_per_step_after_resume(tmp_path):
  path = tmp_path / 'metrics.jsonl'
  lines = [json.dumps({'step': s, 'loss': s}) for s in (5, 10, 15, 20)]
  path.write_text('\n'.join(lines) + '\n{"step": 2')  # and a line cut by a kill
  w = writers.MetricWriter(str(tmp_path), resume_step=10)
  for s in (15, 20):
    w.write(s, {'loss': -s})
  w.close()
  recs = [json.loads(l) for l in path.read_text().splitlines()]
  assert [r['step'] for r in recs] == [5, 10, 15, 20]
  assert [r['loss'] for r in recs] == [5, 10, -15, -20]
  # The resumed run's event file holds what it wrote, after a session START
  # at step 11 telling TensorBoard to drop what an earlier file has from there.
  (events,) = _event_files(tmp_path)
  read = read_events(events)
  assert scalars(read) == [(15, 'loss', -15.0), (20, 'loss', -20.0)]
  starts = [e.step for e in read if e.HasField('session_log')
            and e.session_log.status == e.session_log.START]
  assert starts == [11]


def test_line_plot_draws_a_png_of_the_asked_size(tmp_path):
  from PIL import Image
  path = tmp_path / 'sub' / 'plot.png'
  writers.line_plot(str(path), {'a': ([50, 100, 1000], [3.0, np.nan, 1.0]),
                                'b': ([50, 100], [2.0, 2.5])},
                    'iterations (log)', 'L1', title='t', logx=True, size=(320, 200))
  img = np.asarray(Image.open(path).convert('RGB'))
  assert img.shape == (200, 320, 3)
  # Both series are drawn in colour (matplotlib's first two cycle colours).
  for rgb in ((31, 119, 180), (255, 127, 14)):
    assert (np.abs(img.astype(int) - rgb).sum(-1) < 30).sum() > 20


def test_a_full_disk_names_the_file_and_closing_releases_both(tmp_path):
  """/dev/full fails every write with ENOSPC: the error names metrics.jsonl,
  and close() still closes the event file before raising (nothing is left
  for an exit hook to flush again); quiet=True raises nothing."""
  if not os.path.exists('/dev/full'):
    pytest.skip('needs /dev/full')
  os.symlink('/dev/full', tmp_path / 'metrics.jsonl')
  w = writers.MetricWriter(str(tmp_path))
  with pytest.raises(OSError) as e:
    w.write(1, {'loss': 1.0})
  assert e.value.errno == errno.ENOSPC
  assert e.value.filename == str(tmp_path / 'metrics.jsonl')
  with pytest.raises(OSError) as e:
    w.close()
  assert e.value.errno == errno.ENOSPC
  assert w.jsonl.closed
  with pytest.raises(ValueError):  # the event file is closed too
    w.events.flush()
  w = writers.MetricWriter(str(tmp_path))
  with pytest.raises(OSError):
    w.write(1, {'loss': 1.0})
  w.close(quiet=True)
  assert w.jsonl.closed
