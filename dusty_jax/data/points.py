"""Point cloud files of one sweep, read as named fields and written for tests.

:func:`read_points` returns ``{field name: 1-D array}``, every array of one
length N, always with 'x', 'y', 'z' and whatever else the file holds under
the file's own names, in the file's own dtypes. The format follows the file
name:

  ``.bin``      KITTI velodyne: float32 x, y, z, reflectance (as 'intensity'),
                checked as the KITTI reader checks it (kitti.read_bin).
  ``.pcd.bin``  nuScenes: float32 x, y, z, intensity, ring (ring as float32,
                as in the file).
  ``.pcd``      PCD v0.5-0.7, DATA ascii, binary or binary_compressed (the
                optional pypcd4: ``pip install 'dusty_jax[pcd]'``).
  ``.ply``      PLY, ASCII or binary, the 'vertex' element's properties (plyfile).
  ``.npy``      an (N, 3..5) number array: x, y, z[, intensity[, ring]], or a
                1-D structured array whose field names are kept.
  ``.pcap``     an Ouster recording with its metadata json (ouster.py; needs
                the optional ``ouster-sdk``).

What a reader keeps, so the unfolding can decide (and count) what to drop:

  * The ring-like field is called what the driver calls it: 'ring'
    (Velodyne, nuScenes), 'channel' (Hesai), 'beam' (others);
    :func:`ring_field` picks it. Its numbering is the driver's own (top
    first, bottom first or in firing order): map it by each ring's measured
    elevation, never by an assumed order.
  * nuScenes keeps ~1,600 placeholder points at the origin (0, 0, 0) for
    beams without a return: they are returned as they are.
  * Organized PCD clouds write NaN x, y, z where a beam had no return: kept as
    NaN (a KITTI ``.bin`` with NaN is refused, as the KITTI path always has).
  * Dual-return drivers write two points per firing: all are kept, with the
    file's 'return_type' field where it has one (its codes are the driver's).
  * Other fields keep the driver's units: the VLP-16 sample's 'azimuth' runs
    0-36000 (hundredths of a degree), the PandarXT16's 0-2 pi (radians).
    Angles for the unfolding come from x, y, z.

Every file that cannot be read raises one DataError (a ValueError) naming the
file and the problem.

:func:`write_points` writes fields in each format (through the same libraries
where they write), so tests can write a sweep and read it back.
"""

from __future__ import annotations

import io
import os

import numpy as np
import plyfile

from dusty_jax.data import kitti
from dusty_jax.data import ouster
from dusty_jax.errors import DataError, UserError

# Names drivers give the beam index of a point, in the order they are looked for.
RING_FIELDS = ('ring', 'channel', 'beam')

NUSCENES_FIELDS = ('x', 'y', 'z', 'intensity', 'ring')  # float32 each, in this order.
KITTI_FIELDS = ('x', 'y', 'z', 'intensity')  # 'intensity' is KITTI's reflectance.
NPY_COLUMNS = ('x', 'y', 'z', 'intensity', 'ring')  # of an (N, 3..5) array.

PCD_ENCODINGS = ('ascii', 'binary', 'binary_compressed')
PLY_ENCODINGS = ('binary', 'ascii')

# A PCD header is a dozen short lines; past this many bytes without a DATA
# line the file is not a PCD file.
PCD_MAX_HEADER_BYTES = 65536

PCD_INSTALL = "pip install 'dusty_jax[pcd]'"

# pypcd4 renames each padding field '_' of a PCD header to this prefix and
# random letters; padding carries no data.
_PCD_PADDING = '#$%&~~'


def _suffix(path: str) -> str:
  """The format a file name says: '.pcd.bin', '.bin', '.pcd', '.ply', ..."""
  name = os.path.basename(path).lower()
  if name.endswith('.pcd.bin'):
    return '.pcd.bin'
  return os.path.splitext(name)[1]


def format_of(path: str) -> str | None:
  """The point format a file name says ('.pcd', '.pcd.bin', ...), or None
  for a name no reader here takes."""
  suffix = _suffix(path)
  return suffix if suffix in READERS else None


def read_points(path: str, *, metadata: str | None = None,
                frame: int = 0) -> dict[str, np.ndarray]:
  """The fields of the sweep in ``path``: {name: (N,) array}, with x, y, z.

  The format follows the file name (module docstring). ``metadata`` and
  ``frame`` are for an Ouster ``.pcap`` only (ouster.read_ouster): its
  metadata json (default: the json beside it) and which sweep to read.
  """
  path = os.fspath(path)
  suffix = _suffix(path)
  if suffix not in READERS:
    raise DataError(f'{path}: unknown point cloud format {suffix or "(no extension)"!r}; '
                    f'known: {", ".join(sorted(READERS))}')
  if not os.path.isfile(path):
    raise DataError(f'{path}: no such file')
  if suffix == '.pcap':
    fields = ouster.read_ouster(path, metadata, frame=frame)
  elif metadata is not None or frame:
    raise DataError(f'{path}: metadata and frame are for an Ouster .pcap only')
  else:
    fields = READERS[suffix](path)
  return check_fields(fields, path)


def ring_field(fields: dict[str, np.ndarray], source: str = 'points') -> np.ndarray | None:
  """The beam index of each point as int64, or None if the sweep has none.

  Looks for 'ring', 'channel' and 'beam' (RING_FIELDS), in that order. The
  numbering is the driver's own; a float field (nuScenes) must hold whole
  numbers. ``source`` names the sweep in the error.
  """
  for name in RING_FIELDS:
    if name in fields:
      ring = np.asarray(fields[name])
      if ring.dtype.kind == 'f':
        if not (np.isfinite(ring).all() and (ring == np.round(ring)).all()):
          raise DataError(f'{source}: the ring field {name!r} holds values that are not '
                          'whole numbers')
      elif ring.dtype.kind not in 'iu':
        raise DataError(f'{source}: the ring field {name!r} is of type {ring.dtype}, not a '
                        'number')
      return ring.astype(np.int64)
  return None


def check_fields(fields: dict[str, np.ndarray], path: str) -> dict[str, np.ndarray]:
  """Fields as equal-length 1-D arrays with x, y, z (as floats); DataError
  naming ``path`` otherwise. Every reader's output passes here."""
  missing = [k for k in ('x', 'y', 'z') if k not in fields]
  if missing:
    raise DataError(f'{path}: no {", ".join(missing)} field; fields: '
                    f'{", ".join(fields) or "none"}')
  lengths = {np.shape(v) for v in fields.values()}
  if len(lengths) != 1 or len(next(iter(lengths))) != 1:
    raise DataError(f'{path}: fields must be 1-D arrays of one length, got shapes '
                    f'{sorted(lengths)}')
  for k in ('x', 'y', 'z'):
    if fields[k].dtype.kind != 'f':
      fields[k] = fields[k].astype(np.float64)
  return fields


def _columns(arr: np.ndarray, names) -> dict[str, np.ndarray]:
  """{name: contiguous column} of an (N, len(names)) array."""
  return {k: np.ascontiguousarray(arr[:, i]) for i, k in enumerate(names)}


def _structured(arr: np.ndarray) -> dict[str, np.ndarray]:
  """{name: contiguous 1-D array} of a structured array."""
  return {k: np.ascontiguousarray(arr[k]) for k in arr.dtype.names}


def _read_kitti(path: str) -> dict[str, np.ndarray]:
  try:
    arr = kitti.read_bin(path)
  except ValueError as e:  # its messages name the file already
    raise DataError(str(e)) from None
  return _columns(arr, KITTI_FIELDS)


def _read_nuscenes(path: str) -> dict[str, np.ndarray]:
  size = os.path.getsize(path)
  point_bytes = 4 * len(NUSCENES_FIELDS)
  if size == 0:
    raise DataError(f'{path}: empty file')
  if size % point_bytes:
    raise DataError(f'{path}: size {size} bytes is not a multiple of {point_bytes} '
                    '(float32 x, y, z, intensity, ring per point); truncated or not '
                    'a nuScenes .pcd.bin')
  arr = np.fromfile(path, dtype='<f4').reshape(-1, len(NUSCENES_FIELDS))
  return _columns(arr, NUSCENES_FIELDS)


def _pcd_header(f, path: str) -> tuple[list[str], int]:
  """The header lines of a PCD file up to DATA, and the data's offset."""
  lines = []
  while True:
    raw = f.readline()
    if not raw:
      raise DataError(f'{path}: PCD header without a DATA line')
    if f.tell() > PCD_MAX_HEADER_BYTES:
      raise DataError(f'{path}: no PCD header (no DATA line in the first '
                      f'{PCD_MAX_HEADER_BYTES} bytes)')
    try:
      line = raw.decode('ascii').strip()
    except UnicodeDecodeError:
      raise DataError(f'{path}: not a PCD file (binary bytes in the header)') from None
    if line and not line.startswith('#'):
      lines.append(line)
    if line.upper().startswith('DATA'):
      return lines, f.tell()


def _pypcd4(path: str):
  """pypcd4's module, or one UserError saying how to install it."""
  try:
    # pypcd4 is optional: it brings pydantic and a compiled lzf codec.
    from pypcd4 import pypcd4
  except ImportError:
    raise UserError(f'{path}: PCD files need pypcd4: {PCD_INSTALL}') from None
  return pypcd4


def _read_pcd(path: str) -> dict[str, np.ndarray]:
  """A PCD file through pypcd4, which reads every field type, WIDTH 0
  headers and the three DATA kinds; three gaps are filled here. pypcd4 splits
  ASCII rows at single spaces, so a row with a trailing space or a tab (as
  some writers leave) fails there: ASCII data is read with numpy's
  whitespace splitting and pypcd4's dtype. It reads binary data short of
  POINTS without a word: the size is checked first. And it takes the first
  ten lines of a header as all of it: it is given its own.
  """
  pypcd4 = _pypcd4(path)
  with open(path, 'rb') as f:
    lines, offset = _pcd_header(f, path)
    keys = {line.split()[0].upper() for line in lines}
    for key in ('FIELDS', 'SIZE', 'TYPE', 'POINTS'):
      if key not in keys:
        raise DataError(f'{path}: PCD header has no {key} line')
    kind = lines[-1].split()[1].lower() if len(lines[-1].split()) > 1 else ''
    if kind not in PCD_ENCODINGS:
      raise DataError(f'{path}: PCD DATA {kind!r} is not supported; known: '
                      f'{", ".join(PCD_ENCODINGS)}')
    try:
      meta = pypcd4.MetaData.parse_header(lines)
    except ValueError as e:  # pydantic's ValidationError is a ValueError
      problems = '; '.join(f'{"/".join(map(str, err["loc"])).upper()}: {err["msg"]}'
                           for err in getattr(e, 'errors', lambda: [])()) or str(e)
      raise DataError(f'{path}: bad PCD header ({problems})') from None
    n = len(meta.fields)
    if not len(meta.size) == len(meta.type) == len(meta.count) == n:
      raise DataError(f'{path}: PCD header has {n} FIELDS but {len(meta.size)} SIZE, '
                      f'{len(meta.type)} TYPE and {len(meta.count)} COUNT entries')
    try:
      dtype = meta.build_dtype()
    except KeyError as e:
      kind_, size = e.args[0]
      raise DataError(f'{path}: PCD TYPE {kind_} of SIZE {size} is not supported') from None
    if meta.points == 0:
      data = np.empty(0, dtype)
    elif kind == 'ascii':
      try:
        data = np.loadtxt(f, dtype, ndmin=1)
      except ValueError as e:
        raise DataError(f'{path}: bad PCD ascii data ({e})') from None
    else:
      need = meta.points * dtype.itemsize
      have = os.path.getsize(path) - offset
      if kind == 'binary' and have < need:
        raise DataError(f'{path}: PCD binary data of {have} bytes, short of the {need} '
                        f'that POINTS {meta.points} of {dtype.itemsize} bytes need; truncated')
      # pypcd4 stops reading a header at its tenth line: it is handed the
      # header it writes itself, whatever lines and comments the file had.
      body = io.BytesIO(meta.compose_header().encode() + f.read())
      try:
        data = pypcd4.PointCloud.from_fileobj(body).pc_data
      except Exception as e:  # lzf's and struct's errors, of corrupt data
        raise DataError(f'{path}: bad PCD {kind} data ({type(e).__name__}: {e})') from None
  if len(data) != meta.points:
    raise DataError(f'{path}: PCD header says POINTS {meta.points}, the data holds '
                    f'{len(data)}')
  return {k: v for k, v in _structured(data).items() if not k.startswith(_PCD_PADDING)}


def _read_ply(path: str) -> dict[str, np.ndarray]:
  try:
    ply = plyfile.PlyData.read(path)
  except (plyfile.PlyParseError, ValueError, EOFError, OSError) as e:
    raise DataError(f'{path}: bad PLY file ({e})') from None
  if 'vertex' not in ply:
    raise DataError(f'{path}: PLY file without a vertex element')
  data = ply['vertex'].data
  lists = [k for k in data.dtype.names if data.dtype[k].kind == 'O']
  if lists:
    raise DataError(f'{path}: PLY vertex list properties {lists} are not per-point numbers')
  return _structured(data)


def _read_npy(path: str) -> dict[str, np.ndarray]:
  try:
    arr = np.load(path, allow_pickle=False)
  except (OSError, ValueError) as e:
    raise DataError(f'{path}: not a readable .npy array ({e})') from None
  if not isinstance(arr, np.ndarray):
    arr.close()
    raise DataError(f'{path}: a .npz archive, not a .npy array of points')
  if arr.dtype.names:
    if arr.ndim != 1:
      raise DataError(f'{path}: structured array of shape {arr.shape}, not (N,)')
    return _structured(arr)
  if arr.ndim != 2 or not 3 <= arr.shape[1] <= len(NPY_COLUMNS) or arr.dtype.kind not in 'fiu':
    raise DataError(f'{path}: expected an (N, 3..{len(NPY_COLUMNS)}) array of numbers '
                    f'({", ".join(NPY_COLUMNS)}) or a structured array with named fields, '
                    f'got {arr.dtype} of shape {arr.shape}')
  return _columns(arr, NPY_COLUMNS[:arr.shape[1]])


READERS = {
    '.bin': _read_kitti,
    '.pcd.bin': _read_nuscenes,
    '.pcd': _read_pcd,
    '.ply': _read_ply,
    '.npy': _read_npy,
    '.pcap': ouster.read_ouster,
}


def write_points(path: str, fields: dict[str, np.ndarray], *, encoding: str | None = None):
  """Writes fields {name: (N,) array} in the format its name says.

  ``.pcd`` (pypcd4; ``encoding`` 'binary' by default, 'ascii' or
  'binary_compressed'; ASCII keeps 10 decimals, pypcd4's choice), ``.ply``
  (plyfile; 'binary' by default or 'ascii'; no 64-bit integers in PLY) and
  ``.npy`` (a structured array) keep every field with its dtype.
  ``.pcd.bin`` writes float32 x, y, z, intensity and the ring field
  (:func:`ring_field`); ``.bin`` float32 x, y, z, intensity. Intensity
  missing is written as 0; other fields are left out.
  """
  path = os.fspath(path)
  suffix = _suffix(path)
  if suffix not in WRITERS:
    raise ValueError(f'{path}: cannot write {suffix or "(no extension)"!r}; known: '
                     f'{", ".join(sorted(WRITERS))}')
  encodings = {'.pcd': PCD_ENCODINGS, '.ply': PLY_ENCODINGS}.get(suffix, (None,))
  if encoding is None:
    encoding = encodings[1] if suffix == '.pcd' else encodings[0]
  if encoding not in encodings:
    raise ValueError(f'{path}: encoding {encoding!r} for {suffix}; known: {encodings}')
  fields = {k: np.asarray(v) for k, v in fields.items()}
  check_fields(dict(fields), path)
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  WRITERS[suffix](path, fields, encoding)


def _as_float32(fields, names, path) -> np.ndarray:
  """(N, len(names)) float32 of the named fields; intensity missing is 0."""
  n = len(fields['x'])
  cols = []
  for k in names:
    if k == 'ring':
      v = ring_field(fields, path)
      if v is None:
        raise ValueError(f'{path}: a nuScenes .pcd.bin needs a ring field '
                         f'({", ".join(RING_FIELDS)})')
    else:
      v = fields.get(k, np.zeros(n))
    cols.append(np.asarray(v, np.float32))
  return np.stack(cols, 1)


def _write_kitti(path, fields, encoding):
  kitti.write_bin(path, _as_float32(fields, KITTI_FIELDS, path))


def _write_nuscenes(path, fields, encoding):
  _as_float32(fields, NUSCENES_FIELDS, path).astype('<f4').tofile(path)


def _write_pcd(path, fields, encoding):
  pypcd4 = _pypcd4(path)
  names = list(fields)
  arrays = [fields[k].astype(np.uint8) if fields[k].dtype == bool else fields[k]
            for k in names]
  try:
    cloud = pypcd4.PointCloud.from_points(arrays, names, [a.dtype for a in arrays])
  except KeyError as e:
    raise ValueError(f'{path}: PCD has no type for {e.args[0]}') from None
  cloud.save(path, encoding=pypcd4.Encoding(encoding))


def _write_ply(path, fields, encoding):
  data = np.empty(len(fields['x']), [(k, v.dtype) for k, v in fields.items()])
  for k, v in fields.items():
    data[k] = v
  try:
    vertex = plyfile.PlyElement.describe(data, 'vertex')
  except ValueError as e:
    raise ValueError(f'{path}: {e}') from None
  plyfile.PlyData([vertex], text=encoding == 'ascii').write(path)


def _write_npy(path, fields, encoding):
  data = np.empty(len(fields['x']), [(k, v.dtype) for k, v in fields.items()])
  for k, v in fields.items():
    data[k] = v
  np.save(path, data, allow_pickle=False)


WRITERS = {
    '.bin': _write_kitti,
    '.pcd.bin': _write_nuscenes,
    '.pcd': _write_pcd,
    '.ply': _write_ply,
    '.npy': _write_npy,
}
