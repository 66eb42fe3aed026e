"""MetricWriter: metrics.jsonl and the TensorBoard event file hold what was
written; the pictures label every panel and colour bar."""

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


def _depth_and_probability(rows=2):
  from dusty_jax import get_sensor
  sensor = get_sensor('kitti')
  h, w = sensor.shape
  rng = np.random.default_rng(0)
  depth = [rng.uniform(-0.9, 1.0, (h, w)).astype(np.float32) for _ in range(rows)]
  depth[0][3, :7] = -1.0  # drops
  depth[0][4, 0] = np.nan
  prob = [rng.uniform(0, 1, (h, w)) for _ in range(rows)]
  return sensor, depth, prob


def test_scan_figure_titles_every_panel_and_labels_every_colour_bar():
  sensor, depth, prob = _depth_and_probability()
  fig = writers.scan_figure(
      [writers.Column('target scan', writers.DEPTH, depth),
       writers.Column('measurability', writers.PROBABILITY, prob, 'probability of a return')],
      sensor, row_label='test scan')
  assert writers.figure_labels(fig) == {
      'panels': ['target scan (test scan 1)', 'measurability (test scan 1)',
                 'target scan (test scan 2)', 'measurability (test scan 2)'],
      'colour bars': [writers.COLOUR_BAR[writers.DEPTH], 'probability of a return']}
  assert writers.COLOUR_BAR[writers.DEPTH].startswith('range (m')  # its unit
  panels = [a for a in fig.axes if a.get_label() != '<colorbar>']
  # Depth is drawn as range in metres: 1 / inverse depth, the codec's mapping
  # written out here; drops and NaN are masked (drawn black), nothing else.
  shown = panels[0].images[0].get_array()
  x = depth[0]
  lo, hi = 1 / sensor.max_depth, 1 / sensor.min_depth
  with np.errstate(invalid='ignore'):
    returned = x > -1.0
  np.testing.assert_array_equal(np.ma.getmaskarray(shown), ~returned)
  np.testing.assert_allclose(shown.data[returned], 1 / ((x[returned] + 1) / 2 * (hi - lo) + lo),
                             rtol=1e-5)
  assert panels[0].images[0].norm.vmin == sensor.min_depth
  assert panels[0].images[0].norm.vmax == sensor.max_depth
  assert panels[1].images[0].get_clim() == (0.0, 1.0)
  # The depth bar's ticks are round ranges in metres, labelled as such.
  bar = [a for a in fig.axes if a.get_label() == '<colorbar>'][0]
  ticks = list(bar.get_xticks())
  assert ticks == [1, 2, 5, 10, 20, 50, 100]
  assert [t.get_text() for t in bar.get_xticklabels()] == [f'{t:g}' for t in ticks]


def test_one_row_panels_take_the_column_title_and_the_figure_its_own():
  sensor, depth, _ = _depth_and_probability(rows=1)
  fig = writers.scan_figure([writers.Column('input scan', writers.DEPTH, depth),
                             writers.Column('x_tilde', writers.DEPTH, depth)],
                            sensor, title='scan_0007')
  assert writers.figure_labels(fig)['panels'] == ['input scan', 'x_tilde']
  assert fig._suptitle.get_text() == 'scan_0007'


def test_scan_figure_refuses_ragged_columns_and_unknown_kinds():
  sensor, depth, prob = _depth_and_probability()
  with pytest.raises(ValueError, match='same number of images.*a: 2, b: 1'):
    writers.scan_figure([writers.Column('a', writers.DEPTH, depth),
                         writers.Column('b', writers.DEPTH, depth[:1])], sensor)
  with pytest.raises(ValueError, match="kind 'metres'"):
    writers.scan_figure([writers.Column('a', 'metres', depth)], sensor)


def test_save_figure_writes_the_labels_into_the_png(tmp_path):
  from PIL import Image
  sensor, depth, prob = _depth_and_probability()
  fig = writers.scan_figure([writers.Column('target scan', writers.DEPTH, depth),
                             writers.Column('drop probability', writers.PROBABILITY, prob)],
                            sensor)
  path = tmp_path / 'sub' / 'f.png'
  writers.save_figure(fig, str(path))
  assert writers.read_labels(str(path)) == writers.figure_labels(fig)
  w, h = fig.get_size_inches() * fig.dpi
  assert Image.open(path).size == (round(w), round(h))
  Image.new('RGB', (4, 4)).save(tmp_path / 'bare.png')
  assert writers.read_labels(str(tmp_path / 'bare.png')) == {}
