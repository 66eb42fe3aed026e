"""First hits of rays on a triangle mesh: Embree 4 called directly.

trimesh's Embree intersector (``trimesh.ray.ray_pyembree``, through embreex)
is what the simulated LiDAR was written against, and its answers are the
reference: every cached dataset holds them. Per scan it spends most of its
time outside Embree: embreex copies the mesh into Embree one Python-level
element at a time (its ``mesh_construction.pyx`` indexes a generic ndarray
per vertex and per triangle), and trimesh recomputes and hashes its cached bookkeeping per call.

:func:`first_hits` gives the same answers for less: the library embreex ships
is called through ctypes with the mesh as shared buffers, the same scene
flags and the same float32 inputs (trimesh's scaling to a ~100 unit box), rays
go in 16 at a time (``rtcIntersect16``), and the hit points come from
trimesh's ``planes_lines`` arithmetic on the very arrays ray_pyembree hands it.
tests/test_synthetic.py checks the two agree bit for bit. Given only the faces
that can be first hits (``candidates``; :func:`facing_origin` for a scene)
it builds and searches a smaller tree.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import os

import numpy as np
from trimesh import triangles, util
from trimesh.constants import tol

# --- Embree 4 API (include/embree4/rtcore_*.h) --------------------------------
_GEOMETRY_TYPE_TRIANGLE = 0
_BUFFER_TYPE_INDEX, _BUFFER_TYPE_VERTEX = 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003
_SCENE_FLAG_ROBUST = 1 << 2  # embreex's EmbreeScene sets it (robust=True).
_INVALID_ID = 0xFFFFFFFF
_PACKET = 16                 # rays per rtcIntersect16 call.
# One RTCRayHit16 in float32 words: the ray's 12 fields, then the hit's
# Ng (3), u, v, primID, geomID and instID[1] (embreex's build; its
# rtcore_ray.pxd), each 16 wide; the record is padded to a 64-byte multiple
# with room for instPrimID.
_RAY_FIELDS = 12
_ORG, _DIR, _TFAR, _MASK = 0, 4, 8, 9
_PRIM, _GEOM, _INST = 17, 18, 19
_RECORD = 24 * _PACKET
_ALIGN = 64                  # RTCRayHit16 and its valid mask: RTC_ALIGN(64).
# trimesh.ray.ray_pyembree's _scale: the mesh is scaled to about this size.
_TRIMESH_BOX = 100.0


def _library_path() -> str | None:
  """The Embree 4 library bundled with embreex 4, or None (no embreex, which
  pyproject.toml installs on x86_64 only, or embreex 2 with Embree 2)."""
  try:
    import embreex  # optional: see pyproject.toml
  except ImportError:
    return None
  here = os.path.dirname(embreex.__file__)
  for pattern in ('../embreex.libs/libembree4*', '.dylibs/libembree4*',
                  '../embreex.libs/embree4*.dll', 'embree4*.dll', 'libembree4*'):
    found = sorted(glob.glob(os.path.join(here, pattern)))
    if found:
      return found[0]
  return None


@functools.lru_cache(maxsize=None)
def _api(pid: int):
  """(library, device) for this process; ``pid`` keys it so that a forked
  child makes its own device."""
  path = _library_path()
  if path is None:
    return None
  try:
    lib = ctypes.CDLL(path)
  except OSError:
    return None
  vp = ctypes.c_void_p
  sigs = {
      'rtcNewDevice': (vp, [ctypes.c_char_p]),
      'rtcGetDeviceError': (ctypes.c_int, [vp]),
      'rtcNewScene': (vp, [vp]),
      'rtcSetSceneFlags': (None, [vp, ctypes.c_int]),
      'rtcNewGeometry': (vp, [vp, ctypes.c_int]),
      'rtcSetSharedGeometryBuffer': (None, [vp, ctypes.c_int, ctypes.c_uint, ctypes.c_int, vp,
                                            ctypes.c_size_t, ctypes.c_size_t, ctypes.c_size_t]),
      'rtcCommitGeometry': (None, [vp]),
      'rtcAttachGeometry': (ctypes.c_uint, [vp, vp]),
      'rtcReleaseGeometry': (None, [vp]),
      'rtcCommitScene': (None, [vp]),
      'rtcReleaseScene': (None, [vp]),
      'rtcIntersect16': (None, [vp, vp, vp, vp]),
  }
  for name, (res, args) in sigs.items():
    fn = getattr(lib, name, None)
    if fn is None:
      return None
    fn.restype, fn.argtypes = res, args
  device = lib.rtcNewDevice(None)
  if not device:
    return None
  return lib, device


def available() -> bool:
  """Whether Embree 4 can be called directly here."""
  return _api(os.getpid()) is not None


def _aligned(shape, dtype, fill=np.zeros) -> np.ndarray:
  """``fill`` (np.zeros or np.empty) of ``shape`` whose data starts on a
  64-byte boundary."""
  n = int(np.prod(shape))
  item = np.dtype(dtype).itemsize
  raw = fill(n * item + _ALIGN, np.uint8)
  start = -raw.ctypes.data % _ALIGN
  return raw[start:start + n * item].view(dtype).reshape(shape)


class Rays:
  """Rays from the origin along ``directions`` (n, 3), packed for Embree once:
  the unit directions as ray_pyembree makes them (float64), their float32
  packets and the packets' valid masks."""

  def __init__(self, directions: np.ndarray):
    directions = np.array(directions, dtype=np.float64).reshape(-1, 3)
    self.n = n = len(directions)
    self.unit = util.unitize(directions)
    k = -(-n // _PACKET)
    self.template = _aligned((k, _RECORD), np.float32)
    padded = np.zeros((k * _PACKET, 3), np.float32)
    padded[:n] = self.unit.astype(np.float32)
    for j in range(3):
      self.template[:, _field(_DIR + j)] = padded[:, j].reshape(k, _PACKET)
    self.template[:, _field(_TFAR)] = np.float32(1e37)  # embreex's tfar
    words = self.template.view(np.uint32)
    words[:, _field(_MASK)] = _INVALID_ID  # mask: every bit
    for f in (_PRIM, _GEOM, _INST):
      words[:, _field(f)] = _INVALID_ID
    self.valid = _aligned((k, _PACKET), np.int32)
    self.valid.reshape(-1)[:n] = -1
    for a in (self.unit, self.template, self.valid):
      a.flags.writeable = False


def _field(f: int) -> slice:
  """Columns of field ``f`` in a packet record."""
  return slice(f * _PACKET, (f + 1) * _PACKET)


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
  """trimesh.Trimesh.face_normals of (vertices, faces): unit normals, zero
  for degenerate faces."""
  tri = np.take(vertices, faces, axis=0)
  normals, valid = triangles.normals(triangles=tri, crosses=triangles.cross(tri))
  if valid.all():
    return normals
  padded = np.zeros((len(faces), 3), np.float64)
  padded[valid] = normals
  return padded


def _bounds(vertices: np.ndarray):
  """(min, max) of (n, 3) ``vertices`` over n: the same values as
  ``vertices.min(axis=0)``, about 20 times faster on a transposed copy."""
  columns = np.ascontiguousarray(vertices.T)
  return columns.min(axis=1), columns.max(axis=1)


def _trimesh_scale(vertices: np.ndarray, faces: np.ndarray, bounds) -> float:
  """trimesh.Trimesh.scale: the diagonal of the referenced vertices' box
  (``bounds``: all vertices' :func:`_bounds`)."""
  referenced = np.zeros(len(vertices), dtype=bool)
  referenced[faces] = True
  if not referenced.any():
    return 1.0
  lo, hi = bounds if referenced.all() else _bounds(vertices[referenced])
  scale = float(((hi - lo) ** 2).sum() ** 0.5)
  return 1.0 if scale < tol.zero else scale


def facing_origin(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
  """Per face, False where it turns its back on the origin (its normal, by
  the right-hand rule, points away from it), True otherwise: toward it, or
  edge-on within a generous rounding margin.

  In a mesh of closed, outward-facing parts with the origin outside all of
  them (a scene: scene.py), a ray from the origin enters a part before it
  leaves it, so its first hit is on a face that is True here; Embree need
  only be given those, about 40% of a scene's faces.
  """
  v = np.ascontiguousarray(vertices.T)
  f = np.ascontiguousarray(faces.T)
  a, b, c = (np.take(v, f[k], axis=1) for k in range(3))
  b -= a
  c -= a
  toward = ((b[1] * c[2] - b[2] * c[1]) * a[0] + (b[2] * c[0] - b[0] * c[2]) * a[1]
            + (b[0] * c[1] - b[1] * c[0]) * a[2])
  # Rounding errs by less than about 10 eps |a| |b| |c| (2e-15 of it); the
  # margin is 1e-12 of it (L1 norms, which bound the L2 ones).
  margin = 1e-12 * np.abs(a).sum(0) * np.abs(b).sum(0) * np.abs(c).sum(0)
  return toward <= margin


def first_hits(vertices: np.ndarray, faces: np.ndarray, rays: Rays,
               candidates: np.ndarray | None = None):
  """The first hit of each of ``rays`` on the mesh (vertices, faces).

  Returns ``(index_tri, index_ray, locations, normals)``: what
  ``ray_pyembree.RayMeshIntersector(mesh).intersects_id(zeros, directions,
  multiple_hits=False, return_locations=True)`` returns for the same
  directions, bit for bit, and the face normal of each hit (trimesh's
  ``face_normals[index_tri]``, computed for the hit faces only: a scene's
  rays hit a few hundred of its ~12,000 faces). Raises RuntimeError where
  Embree cannot be called (see :func:`available`).

  ``candidates`` (indices into ``faces``; default all) are the faces that
  can be first hits, and the only ones Embree is given (see
  :func:`facing_origin`); the mesh's frame is still trimesh's for all of
  them. The answers are then the same unless a ray meets two faces at one
  distance (a ridge, or faces that overlap in one plane) and Embree picked
  one left out.
  """
  api = _api(os.getpid())
  if api is None:
    raise RuntimeError('Embree 4 (from embreex) cannot be loaded here')
  vertices = np.asarray(vertices, np.float64)
  faces = np.asarray(faces)
  prim = _first_prims(api, vertices, faces, rays, candidates)
  index_ray = np.flatnonzero(prim != _INVALID_ID)
  index_tri = np.take(prim, index_ray).astype(np.int64)
  if candidates is not None:
    index_tri = np.take(candidates, index_tri)
  normals = _hit_normals(vertices, faces, index_tri)
  return _on_planes(vertices, faces, rays, index_tri, index_ray, normals)


def _first_prims(api, vertices, faces, rays: Rays, candidates) -> np.ndarray:
  """(rays.n,) uint32: per ray, the index into ``faces[candidates]`` of the
  first face it hits, or _INVALID_ID. The mesh and the rays go in as
  ray_pyembree._EmbreeWrap gives them: float32 of (x - min vertex) * 100 /
  trimesh's scale of the whole mesh."""
  bounds = _bounds(vertices)
  origin = bounds[0]
  scale = float(_TRIMESH_BOX / _trimesh_scale(vertices, faces, bounds))
  given = faces if candidates is None else faces[candidates]
  vbuf = np.empty((len(vertices), 4), np.float32)  # stride 16: padded float3
  vbuf[:, :3] = (vertices - origin) * scale
  vbuf[:, 3] = 0
  fbuf = np.empty((len(given), 4), np.uint32)
  fbuf[:, :3] = given
  fbuf[:, 3] = 0
  packets = _aligned(rays.template.shape, np.float32, np.empty)
  packets[:] = rays.template
  ray_origin = ((np.zeros(3) - origin) * scale).astype(np.float32)
  for j in range(3):
    packets[:, _field(_ORG + j)] = ray_origin[j]
  _intersect(api, vbuf, fbuf, packets, rays.valid)
  return packets.view(np.uint32)[:, _field(_PRIM)].reshape(-1)[:rays.n]


def _intersect(api, vbuf: np.ndarray, fbuf: np.ndarray, packets: np.ndarray,
               valid: np.ndarray):
  """Builds an Embree scene of one triangle geometry over the shared
  buffers ``vbuf`` (vertices) and ``fbuf`` (faces) and intersects the ray
  ``packets`` (their ``valid`` masks) with it, writing the hits into them."""
  lib, device = api
  scene = lib.rtcNewScene(device)
  try:
    lib.rtcSetSceneFlags(scene, _SCENE_FLAG_ROBUST)
    geom = lib.rtcNewGeometry(device, _GEOMETRY_TYPE_TRIANGLE)
    lib.rtcSetSharedGeometryBuffer(geom, _BUFFER_TYPE_VERTEX, 0, _FORMAT_FLOAT3,
                                   vbuf.ctypes.data, 0, vbuf.strides[0], len(vbuf))
    lib.rtcSetSharedGeometryBuffer(geom, _BUFFER_TYPE_INDEX, 0, _FORMAT_UINT3,
                                   fbuf.ctypes.data, 0, fbuf.strides[0], len(fbuf))
    lib.rtcCommitGeometry(geom)
    lib.rtcAttachGeometry(scene, geom)
    lib.rtcReleaseGeometry(geom)
    lib.rtcCommitScene(scene)
    error = lib.rtcGetDeviceError(device)
    if error:
      raise RuntimeError(f'Embree failed to build a scene of {len(fbuf)} '
                         f'triangles: RTCError {error}')
    intersect16 = lib.rtcIntersect16
    base, step = packets.ctypes.data, packets.strides[0]
    mask, mask_step = valid.ctypes.data, valid.strides[0]
    for i in range(len(packets)):
      intersect16(mask + i * mask_step, scene, base + i * step, None)
  finally:
    lib.rtcReleaseScene(scene)


def _hit_normals(vertices, faces, index_tri) -> np.ndarray:
  """face_normals(vertices, faces)[index_tri], computed for the faces hit."""
  hit_faces = np.flatnonzero(np.bincount(index_tri, minlength=len(faces)))
  slot = np.empty(len(faces), np.int64)
  slot[hit_faces] = np.arange(len(hit_faces))
  return np.take(face_normals(vertices, np.take(faces, hit_faces, axis=0)),
                 np.take(slot, index_tri), axis=0)


def _on_planes(vertices, faces, rays: Rays, index_tri, index_ray, normals):
  """ray_pyembree.intersects_id's first pass: the hit points on the faces'
  planes by trimesh's intersections.planes_lines, its float64 operations
  for lines through the origin (np.take: numpy's row indexing is slower),
  and rays nearly parallel to their face dropped. Returns
  ``(index_tri, index_ray, locations, normals)`` of the hits kept."""
  directions = np.take(rays.unit, index_ray, axis=0)
  plane_origins = np.take(vertices, np.take(faces[:, 0], index_tri), axis=0)
  projection_ori = util.diagonal_dot(plane_origins, normals)
  projection_dir = util.diagonal_dot(directions, normals)
  ok = np.flatnonzero(np.abs(projection_dir) > 1e-5)
  distance = np.divide(projection_ori[ok], projection_dir[ok])
  locations = np.take(directions, ok, axis=0) * distance.reshape((-1, 1))
  locations += 0.0  # planes_lines adds the (zero) line origins: -0.0 to 0.0
  return index_tri[ok], index_ray[ok], locations, np.take(normals, ok, axis=0)
