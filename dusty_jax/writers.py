"""Where metrics and pictures go: JSONL, TensorBoard event files, PNG.

Every picture a command writes is a labelled matplotlib figure
(:func:`scan_figure`): one titled panel per range image, and under each
column a colour bar in metres (depth) or in probability. :func:`save_grid`
(bare tiles, no labels) is left for the benchmarks' contact sheets.

The event files are written with tensorboardX's synchronous ``EventsWriter``;
neither TensorFlow nor clu is needed. Not its ``SummaryWriter``: that one
writes from a thread and flushes again at exit, so a full disk, already
reported in one line, would end in tracebacks from its exit hook.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import time
from typing import Sequence

import numpy as np
from PIL import Image
from tensorboardX import event_file_writer, summary
from tensorboardX.proto import event_pb2

from dusty_jax import codec, files
from dusty_jax.sensor import SensorSpec, check_spec


class MetricWriter:
  """Scalars to ``metrics.jsonl`` and a TensorBoard event file in workdir."""

  def __init__(self, workdir: str, enabled: bool = True, resume_step: int = 0):
    """``resume_step``: the step training resumes from; records written after
    it by an interrupted run are dropped, so each step has one record."""
    self.enabled = enabled
    if not enabled:
      return
    os.makedirs(workdir, exist_ok=True)
    path = os.path.join(workdir, 'metrics.jsonl')
    if os.path.isfile(path):
      keep = []
      with open(path) as f:
        for line in f:
          try:
            if json.loads(line)['step'] <= resume_step:
              keep.append(line if line.endswith('\n') else line + '\n')
          except (ValueError, KeyError):
            pass  # a line cut short by a kill
      with files.atomic_write(path) as f:
        f.writelines(keep)
    self.jsonl_path = path
    self.jsonl = open(path, 'a')
    self.events = event_file_writer.EventsWriter(os.path.join(workdir, 'events'))
    self.events_path = self.events._file_name  # pylint: disable=protected-access
    if resume_step:
      # Tell TensorBoard to drop what an interrupted run logged after the
      # checkpoint (it reads the earlier event file too).
      self.events.write_event(event_pb2.Event(
          step=resume_step + 1, wall_time=time.time(),
          session_log=event_pb2.SessionLog(status=event_pb2.SessionLog.START)))

  def write(self, step: int, scalars: dict):
    if not self.enabled:
      return
    now = time.time()
    scalars = {k: float(v) for k, v in scalars.items()}
    with self._naming(self.jsonl_path):
      self.jsonl.write(json.dumps({'step': step, 'time': now, **scalars}) + '\n')
    for k, v in scalars.items():
      with self._naming(self.events_path):
        self.events.write_event(event_pb2.Event(
            step=step, wall_time=now, summary=summary.scalar(k, v)))
    self.flush()

  def flush(self):
    if self.enabled:
      with self._naming(self.jsonl_path):
        self.jsonl.flush()
      with self._naming(self.events_path):
        self.events.flush()

  def close(self, quiet: bool = False):
    """Closes both files, each even if the other fails (e.g. on a full
    disk); then raises the first error unless ``quiet``."""
    if not self.enabled:
      return
    first = None
    for path, f in ((self.jsonl_path, self.jsonl), (self.events_path, self.events)):
      try:
        with self._naming(path):
          f.close()
      except OSError as e:
        first = first or e
    if first is not None and not quiet:
      raise first

  @staticmethod
  @contextlib.contextmanager
  def _naming(path):
    """An OSError without a file name (a flush) gets ``path``."""
    try:
      yield
    except OSError as e:
      if e.filename is None and e.errno is not None:
        raise OSError(e.errno, e.strerror, path) from e
      raise


# ----------------------------------------------------------------------------
# Pictures.
# ----------------------------------------------------------------------------

# Anchor colours of a perceptually ordered map (dark blue -> yellow).
_ANCHORS = np.array([[48, 18, 59], [70, 107, 227], [40, 187, 236],
                     [50, 241, 152], [164, 252, 60], [237, 208, 58],
                     [251, 128, 34], [210, 49, 5], [122, 4, 3]], np.float32)


def colorize(values, lo: float, hi: float, invalid=None) -> np.ndarray:
  """(H, W) values -> (H, W, 3) uint8; ``invalid`` pixels are black."""
  v = np.clip((np.asarray(values, np.float32) - lo) / max(hi - lo, 1e-12), 0, 1)
  pos = v * (len(_ANCHORS) - 1)
  i = np.minimum(pos.astype(np.int64), len(_ANCHORS) - 2)
  t = (pos - i)[..., None]
  rgb = _ANCHORS[i] * (1 - t) + _ANCHORS[i + 1] * t
  if invalid is not None:
    rgb[np.asarray(invalid)] = 0
  return rgb.astype(np.uint8)


def save_grid(path: str, rows: list[list[np.ndarray]], scale: int = 2,
              gap: int = 2):
  """Saves a grid of (H, W, 3) uint8 tiles as one PNG (rows of tiles)."""
  h, w = rows[0][0].shape[:2]
  ncol = max(len(r) for r in rows)
  canvas = np.full((len(rows) * (h + gap) - gap, ncol * (w + gap) - gap, 3),
                   255, np.uint8)
  for i, r in enumerate(rows):
    for j, tile in enumerate(r):
      canvas[i * (h + gap): i * (h + gap) + h, j * (w + gap): j * (w + gap) + w] = tile
  img = Image.fromarray(canvas)
  if scale != 1:
    img = img.resize((img.width * scale, img.height * scale), Image.NEAREST)
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  img.save(path)


def inv_depth_tile(x, alpha: float = -1.0):
  """Normalised inverse depth in [-1, 1] -> colour tile, drops black."""
  x = np.asarray(x)
  return colorize(x, -1.0, 1.0, invalid=x <= alpha)


def prob_tile(p):
  return colorize(np.asarray(p), 0.0, 1.0)


def line_plot(path: str, series: dict, xlabel: str, ylabel: str, title: str = '',
              logx: bool = False, size=(640, 400)):
  """A small line chart as PNG (matplotlib). ``series``: {name: (xs, ys)};
  ``size`` in pixels. Non-finite y values are left out."""
  from matplotlib.figure import Figure  # no pyplot: no global state, no GUI
  dpi = 100
  fig = Figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
  ax = fig.add_subplot()
  for name, (xs, ys) in series.items():
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    ok = np.isfinite(ys)
    ax.plot(xs[ok], ys[ok], 'o-', ms=4, label=name)
  if logx:
    ax.set_xscale('log')
  ticks = np.unique(np.concatenate([np.asarray(x, float) for x, _ in series.values()]))
  if len(ticks) <= 12:  # label the measured x values themselves
    ax.set_xticks(ticks, [f'{v:g}' for v in ticks])
    ax.minorticks_off()
  ax.set_xlabel(xlabel)
  ax.set_ylabel(ylabel)
  if title:
    ax.set_title(title)
  ax.grid(alpha=0.3)
  ax.legend(fontsize=8)
  fig.tight_layout()
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  fig.savefig(path)


# ----------------------------------------------------------------------------
# Labelled figures of range images.
# ----------------------------------------------------------------------------

DEPTH = 'depth'              # normalised inverse depth; drawn as range in metres, drops black
PROBABILITY = 'probability'  # values in [0, 1]

# What each kind's colour bar says, with its units.
COLOUR_BAR = {DEPTH: 'range (m, log scale); black: no return',
              PROBABILITY: 'probability (0 to 1)'}

# Colour-bar ticks in metres; those inside a sensor's range are drawn.
_METRE_TICKS = (1, 2, 5, 10, 20, 50, 100, 200)
# A figure's sizes, in inches (at 100 dpi): a panel is as wide as its scan's
# columns at 80 per inch, within these bounds; above each panel room for its
# title, under each column room for its colour bar.
_PANEL_WIDTH, _COLUMNS_PER_INCH = (3.2, 8.0), 80
_TITLE_INCHES, _BAR_INCHES, _BAR_ROOM_INCHES = 0.35, 0.1, 0.75


@dataclasses.dataclass(frozen=True)
class Column:
  """One column of a :func:`scan_figure`: a kind of image, one per row.

  ``images``: (H, W) arrays, one per row (scan); ``kind``: DEPTH for
  normalised inverse depth (drawn as range in metres, no return black),
  PROBABILITY for values in [0, 1]; ``label``: the colour bar's text, COLOUR_BAR[kind] by
  default."""
  title: str
  kind: str
  images: Sequence[np.ndarray]
  label: str = ''


def range_image(x, sensor: SensorSpec) -> np.ma.MaskedArray:
  """(H, W) normalised inverse depth -> range in metres (the codec's
  decode), masked where nothing returned (drops, beyond range, NaN)."""
  depth, valid = codec.decode(np.asarray(x, np.float32), sensor)
  return np.ma.masked_array(np.asarray(depth), ~np.asarray(valid))


def scan_figure(columns: Sequence[Column], sensor: SensorSpec, row_label: str = 'scan',
                title: str = ''):
  """A matplotlib Figure of range images: one row per scan, one column per
  :class:`Column`, each panel titled '<column title> (<row label> <i>)' (the
  column's title alone for one row), ``title`` above all, and
  under each column a colour bar with its units. Depth is drawn as range in
  metres on a log scale over ``sensor``'s range (near: red, far: blue; no
  return: black), probabilities on 0 to 1. Pass it to :func:`save_figure`,
  or read its axes."""
  check_spec(sensor)
  # Here: matplotlib's import cost, for commands that draw a picture only.
  # Figure, not pyplot: no global state, no GUI.
  from matplotlib import colormaps, colors
  from matplotlib.figure import Figure
  rows = len(columns[0].images) if columns else 0
  if not rows or any(len(c.images) != rows for c in columns):
    raise ValueError('scan_figure: every column needs the same number of images (> 0), got '
                     + ', '.join(f'{c.title}: {len(c.images)}' for c in columns))
  h, w = np.shape(columns[0].images[0])
  panel_w = float(np.clip(w / _COLUMNS_PER_INCH, *_PANEL_WIDTH))
  panel_h = panel_w * h / w
  fig = Figure(figsize=(panel_w * len(columns) + 0.4,
                        (panel_h + _TITLE_INCHES) * rows + _BAR_ROOM_INCHES
                        + (_TITLE_INCHES if title else 0)),
               dpi=100, layout='constrained')
  axes = np.asarray(fig.subplots(rows, len(columns), squeeze=False))
  norms = {DEPTH: colors.LogNorm(sensor.min_depth, sensor.max_depth),
           PROBABILITY: colors.Normalize(0.0, 1.0)}
  cmaps = {DEPTH: colormaps['turbo_r'].with_extremes(bad='black'),
           PROBABILITY: colormaps['turbo']}
  ticks = [m for m in _METRE_TICKS if sensor.min_depth < m < sensor.max_depth]
  for j, col in enumerate(columns):
    if col.kind not in COLOUR_BAR:
      raise ValueError(f'column {col.title!r}: kind {col.kind!r}, expected one of '
                       f'{sorted(COLOUR_BAR)}')
    for i, image in enumerate(col.images):
      image = (range_image(image, sensor) if col.kind == DEPTH
               else np.asarray(image, np.float32))
      ax = axes[i, j]
      shown = ax.imshow(image, cmap=cmaps[col.kind], norm=norms[col.kind],
                        interpolation='nearest', aspect='auto')
      ax.set_title(f'{col.title} ({row_label} {i + 1})' if rows > 1 else col.title, fontsize=9)
      ax.set_xticks([])
      ax.set_yticks([])
    column_h = rows * (panel_h + _TITLE_INCHES)
    bar = fig.colorbar(shown, ax=list(axes[:, j]), location='bottom',
                       fraction=_BAR_INCHES / column_h, aspect=0.8 * panel_w / _BAR_INCHES)
    bar.set_label(col.label or COLOUR_BAR[col.kind], fontsize=8)
    if col.kind == DEPTH:
      bar.set_ticks(ticks, labels=[f'{m:g}' for m in ticks])
      bar.minorticks_off()
    bar.ax.tick_params(labelsize=8)
  if title:
    fig.suptitle(title, fontsize=10)
  return fig


def figure_labels(fig) -> dict:
  """What a Figure's reader is told: its panels' titles and its colour bars'
  labels, in drawing order."""
  bars = [a for a in fig.axes if a.get_label() == '<colorbar>']
  return {'panels': [a.get_title() for a in fig.axes if a not in bars],
          'colour bars': [a.get_xlabel() or a.get_ylabel() for a in bars]}


def save_figure(fig, path: str):
  """Writes a matplotlib Figure as PNG, making its folder. The PNG's
  'Description' text holds :func:`figure_labels` as JSON (read it back with
  :func:`read_labels`)."""
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  fig.savefig(path, metadata={'Description': json.dumps(figure_labels(fig))})


def read_labels(path: str) -> dict:
  """:func:`figure_labels` of a PNG written by :func:`save_figure`; {} for
  another PNG."""
  with Image.open(path) as image:
    text = image.text.get('Description')
  return json.loads(text) if text else {}
