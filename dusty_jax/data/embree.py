"""First hits of rays on a triangle mesh: Embree 4 called directly.

trimesh's Embree intersector (``trimesh.ray.ray_pyembree``, through embreex)
is what the simulated LiDAR was written against, and its answers are the
reference: every cached dataset holds them. Per scan it spends most of its
time outside Embree: embreex copies the mesh into Embree one Python-level
element at a time (its ``mesh_construction.pyx`` indexes a generic ndarray
per vertex and per triangle, about 10 ms for a 12,000-triangle scene), and
trimesh recomputes and hashes its cached bookkeeping per call.

:func:`first_hits` gives the same answers for less: the library embreex ships
is called through ctypes with the mesh as shared buffers, the same scene
flags and the same float32 inputs (trimesh's scaling to a ~100 unit box), rays
go in 16 at a time (``rtcIntersect16``), and the hit points come from
trimesh's own ``planes_lines`` on the very arrays ray_pyembree hands it.
tests/test_synthetic.py checks the two agree bit for bit.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import os

import numpy as np
from trimesh import intersections, triangles, util
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


def _aligned(shape, dtype) -> np.ndarray:
  """Zeros of ``shape`` whose data starts on a 64-byte boundary."""
  n = int(np.prod(shape))
  item = np.dtype(dtype).itemsize
  raw = np.zeros(n * item + _ALIGN, np.uint8)
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
  tri = vertices[faces]
  normals, valid = triangles.normals(triangles=tri, crosses=triangles.cross(tri))
  if valid.all():
    return normals
  padded = np.zeros((len(faces), 3), np.float64)
  padded[valid] = normals
  return padded


def _trimesh_scale(vertices: np.ndarray, faces: np.ndarray) -> float:
  """trimesh.Trimesh.scale: the diagonal of the referenced vertices' box."""
  referenced = np.zeros(len(vertices), dtype=bool)
  referenced[faces] = True
  used = vertices if referenced.all() else vertices[referenced]
  if len(used) == 0:
    return 1.0
  extents = np.ptp(np.array([used.min(axis=0), used.max(axis=0)]), axis=0)
  scale = float((extents ** 2).sum() ** 0.5)
  return 1.0 if scale < tol.zero else scale


def first_hits(vertices: np.ndarray, faces: np.ndarray, rays: Rays):
  """The first hit of each of ``rays`` on the mesh (vertices, faces).

  Returns ``(index_tri, index_ray, locations, normals)``: what
  ``ray_pyembree.RayMeshIntersector(mesh).intersects_id(zeros, directions,
  multiple_hits=False, return_locations=True)`` returns for the same
  directions, bit for bit, and the face normal of each hit (trimesh's
  ``face_normals[index_tri]``, computed for the hit faces only: a scene's
  rays hit a few hundred of its ~12,000 faces). Raises RuntimeError where
  Embree cannot be called (see :func:`available`).
  """
  api = _api(os.getpid())
  if api is None:
    raise RuntimeError('Embree 4 (from embreex) cannot be loaded here')
  lib, device = api
  vertices = np.asarray(vertices, np.float64)
  faces = np.asarray(faces)

  # ray_pyembree._EmbreeWrap: float32 of (v - min v) * 100 / trimesh scale.
  origin = vertices.min(axis=0)
  scale = float(_TRIMESH_BOX / _trimesh_scale(vertices, faces))
  vbuf = np.empty((len(vertices), 4), np.float32)  # stride 16: padded float3
  vbuf[:, :3] = (vertices - origin) * scale
  vbuf[:, 3] = 0
  fbuf = np.empty((len(faces), 4), np.uint32)
  fbuf[:, :3] = faces
  fbuf[:, 3] = 0
  packets = _aligned(rays.template.shape, np.float32)
  packets[:] = rays.template
  ray_origin = ((np.zeros(3) - origin) * scale).astype(np.float32)
  for j in range(3):
    packets[:, _field(_ORG + j)] = ray_origin[j]

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
      raise RuntimeError(f'Embree failed to build a scene of {len(faces)} '
                         f'triangles: RTCError {error}')
    intersect16 = lib.rtcIntersect16
    base, step = packets.ctypes.data, packets.strides[0]
    mask, mask_step = rays.valid.ctypes.data, rays.valid.strides[0]
    for i in range(len(packets)):
      intersect16(mask + i * mask_step, scene, base + i * step, None)
  finally:
    lib.rtcReleaseScene(scene)

  prim = packets.view(np.uint32)[:, _field(_PRIM)].reshape(-1)[:rays.n]
  hit = prim != _INVALID_ID
  index_ray = np.flatnonzero(hit)
  index_tri = prim[hit].astype(np.int64)
  # ray_pyembree.intersects_id, first pass: hit points on the faces' planes,
  # rays nearly parallel to their face dropped.
  hit_faces = np.flatnonzero(np.bincount(index_tri, minlength=len(faces)))
  slot = np.empty(len(faces), np.int64)
  slot[hit_faces] = np.arange(len(hit_faces))
  normals = face_normals(vertices, faces[hit_faces])[slot[index_tri]]
  locations, ok = intersections.planes_lines(
      plane_origins=vertices[faces[index_tri, 0]],
      plane_normals=normals,
      line_origins=np.zeros((len(index_ray), 3)),
      line_directions=rays.unit[index_ray])
  return index_tri[ok], index_ray[ok], locations, normals[ok]
