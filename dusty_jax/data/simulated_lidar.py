"""A simulated LiDAR: one ray per pixel into a scene (scene.py), and drops.

The sensor sits ``sensor.mount_height`` above the road on the ego car, and
casts one ray per pixel of the range image at the sensor's nominal angles.
The first hits are trimesh's Embree intersector's (``embreex``); data/embree.py
gives the same answers faster by calling Embree directly with only the faces
toward the sensor (where a ray met an edge between such a face and one turned
away, Embree could return either: 2 of the default data's 39 million pixels
changed with that), and without embreex trimesh's pure-numpy intersector
stands in.

Point-drop model, per pixel (all probabilities are of *no* return):
  * geometry: no hit (sky), a hit at or beyond ``max_depth``, at or closer
    than ``min_depth``, or on the ego vehicle (its own shadow) -> dropped
    with probability 1;
  * energy: the return's signal ``E = rho * cos(incidence) * (R0 / r)^2``
    (lidar equation for a Lambertian target of reflectivity rho) gives a
    detection probability ``1 - exp(-E / E_MIN)``;
  * surface: glass mostly transmits (detection x GLASS_FACTOR), specular
    paint loses the return at grazing angles (x ``1 - s (1 - cos)^4``),
    foliage is partly see-through (x FOLIAGE_FACTOR);
  * a small random dropout (RANDOM_DROPOUT) on every pixel.
The observed scan samples drops from that probability and adds Gaussian
range noise (RANGE_NOISE_M). Ground truth kept per pixel: the complete depth
(noise-free, 0 where nothing can return) and the drop probability.
"""

from __future__ import annotations

import dataclasses
import functools
import os

import numpy as np

from dusty_jax.data import embree, scene
from dusty_jax.sensor import SensorSpec

# --- Drop model constants ----------------------------------------------------
R0 = 30.0             # reference range of the energy model (m).
E_MIN = 0.02          # signal at which detection probability is 1 - 1/e.
GLASS_FACTOR = 0.12   # share of returns from glass.
FOLIAGE_FACTOR = 0.7  # share of returns from a canopy.
RANDOM_DROPOUT = 0.01
RANGE_NOISE_M = 0.02  # 1-sigma range noise (m).


def has_embree() -> bool:
  try:
    import embreex  # noqa: F401
    return True
  except ImportError:
    return False


def ray_directions(sensor: SensorSpec) -> np.ndarray:
  """(H, W, 3) unit vectors at the sensor's nominal angles."""
  el, az = sensor.nominal_angles().astype(np.float64)
  return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                   np.sin(el)], -1)


# Ways to find the first hits (see the module docstring): Embree called
# directly, trimesh's Embree intersector (the reference), trimesh's numpy one.
RAYCASTERS = ('embree', 'pyembree', 'numpy')


def default_raycaster() -> str:
  if embree.available():
    return 'embree'
  return 'pyembree' if has_embree() else 'numpy'


@functools.lru_cache(maxsize=8)
def _flat_directions(sensor: SensorSpec) -> np.ndarray:
  d = ray_directions(sensor).reshape(-1, 3)
  d.flags.writeable = False
  return d


@functools.lru_cache(maxsize=8)
def _embree_rays(sensor: SensorSpec) -> embree.Rays:
  return embree.Rays(_flat_directions(sensor))


def first_hits(mesh, sensor: SensorSpec, raycaster: str | None = None):
  """(index_tri, index_ray, locations, normals) of each pixel's ray's first
  hit on ``mesh`` (a scene: scene.py), ``normals`` the hit faces' normals;
  rays that hit nothing are left out. Direct Embree is given only the faces
  toward the sensor (embree.facing_origin), a third faster."""
  raycaster = raycaster or default_raycaster()
  if raycaster not in RAYCASTERS:
    raise ValueError(f'unknown raycaster {raycaster!r}; known: {RAYCASTERS}')
  if raycaster == 'embree':
    vertices, faces = mesh.vertices.view(np.ndarray), mesh.faces.view(np.ndarray)
    return embree.first_hits(vertices, faces, _embree_rays(sensor),
                             np.flatnonzero(embree.facing_origin(vertices, faces)))
  dirs = _flat_directions(sensor)
  tri, ray, loc = intersector(mesh, raycaster == 'pyembree').intersects_id(
      np.zeros_like(dirs), dirs, multiple_hits=False, return_locations=True)
  return tri, ray, loc, mesh.face_normals[tri]


def intersector(mesh, use_embree: bool | None = None):
  use_embree = has_embree() if use_embree is None else use_embree
  if use_embree:
    from trimesh.ray import ray_pyembree
    return ray_pyembree.RayMeshIntersector(mesh)
  from trimesh.ray import ray_triangle
  return ray_triangle.RayMeshIntersector(mesh)


@dataclasses.dataclass
class Scan:
  """One simulated scan; all (H, W)."""
  depth: np.ndarray      # observed metric depth, 0 where dropped.
  complete: np.ndarray   # noise-free depth a perfect sensor sees, 0 = none.
  drop_prob: np.ndarray  # probability of no return.
  material: np.ndarray   # material id hit, -1 for sky.
  incidence_cos: np.ndarray
  kind: str = ''


def drop_probability(hit, rng_dist, cos_inc, material, sensor: SensorSpec):
  """Probability of no return per pixel (see the module docstring)."""
  mat = np.where(hit, material, 0)
  geometric = (~hit) | (rng_dist >= sensor.max_depth) | (
      rng_dist <= sensor.min_depth) | scene.EGO[mat]
  r = np.maximum(rng_dist, 1e-3)
  energy = scene.REFLECTIVITY[mat] * cos_inc * (R0 / r) ** 2
  p_det = 1.0 - np.exp(-energy / E_MIN)
  p_det *= np.where(scene.GLASS[mat], GLASS_FACTOR, 1.0)
  p_det *= 1.0 - scene.SPECULAR[mat] * (1.0 - cos_inc) ** 4
  p_det *= np.where(scene.FOLIAGE[mat], FOLIAGE_FACTOR, 1.0)
  p_det *= 1.0 - RANDOM_DROPOUT
  return np.where(geometric, 1.0, 1.0 - p_det)


def render_scan(seed: int, sensor: SensorSpec, kind: str | None = None,
                raycaster: str | None = None) -> Scan:
  """Builds scene ``seed`` and simulates one scan of it (``raycaster``: one
  of RAYCASTERS, default the fastest available)."""
  mesh, material, info = scene.build_scene(seed, kind, sensor.mount_height)
  dirs = _flat_directions(sensor)
  tri, ray, loc, hit_normals = first_hits(mesh, sensor, raycaster)
  n = len(dirs)
  dist = np.full(n, np.inf)
  mat = np.full(n, -1, np.int64)
  cos_inc = np.zeros(n)
  dist[ray] = np.linalg.norm(loc, axis=1)
  mat[ray] = np.take(material, tri)
  cos_inc[ray] = np.abs(np.einsum('ij,ij->i', hit_normals, np.take(dirs, ray, axis=0)))
  hit = mat >= 0
  p_drop = drop_probability(hit, dist, cos_inc, mat, sensor)
  rng = np.random.default_rng((seed, 1))
  complete = np.where(p_drop < 1.0, dist, 0.0)
  observed = complete + rng.normal(0.0, RANGE_NOISE_M, n)
  keep = (rng.uniform(size=n) >= p_drop) & (observed > sensor.min_depth) & (
      observed < sensor.max_depth)
  observed = np.where(keep, observed, 0.0)
  shape = sensor.shape
  return Scan(observed.reshape(shape).astype(np.float32),
              complete.reshape(shape).astype(np.float32),
              p_drop.reshape(shape).astype(np.float32),
              mat.reshape(shape), cos_inc.reshape(shape).astype(np.float32),
              info['kind'])


def render_arrays(job: tuple[int, SensorSpec]):
  """(observed, complete, drop_prob) of ``render_scan(*job)``: a worker's task
  in synthetic.simulate (here, so that a worker does not import JAX)."""
  s = render_scan(*job)
  return s.depth, s.complete, s.drop_prob


def render_into(job: tuple[int, SensorSpec, tuple[str, str, str], int, int]):
  """Writes ``render_arrays((seed, sensor))`` as row ``row`` of three
  (N, H, W) float32 .npy files ``paths`` (observed, complete, drop_prob),
  whose data start ``offset`` bytes in: a worker's task in
  synthetic.write_dataset, which then receives nothing but the row. (Plain
  writes: a full disk raises OSError here, where a memory map's write would
  kill the worker.)"""
  seed, sensor, paths, offset, row = job
  for path, arr in zip(paths, render_arrays((seed, sensor))):
    fd = os.open(path, os.O_WRONLY)
    try:
      os.pwrite(fd, arr.tobytes(), offset + row * arr.nbytes)
    finally:
      os.close(fd)
  return row


def to_sensor_order(depth: np.ndarray, sensor: SensorSpec) -> np.ndarray:
  """(N, 4) points of a depth image in KITTI sensor order (see data/unfolding.py).

  Rings top first; each ring counter-clockwise from straight ahead. Points
  sit at the sensor's nominal angles, so unfolding reproduces ``depth``.
  """
  dirs = ray_directions(sensor)
  w = sensor.width
  order = np.concatenate([np.arange(w // 2 - 1, -1, -1),
                          np.arange(w - 1, w // 2 - 1, -1)])
  d = depth[:, order]
  pts = (d[..., None] * dirs[:, order]).reshape(-1, 3)
  keep = d.reshape(-1) > 0
  refl = np.zeros((keep.sum(), 1), np.float32)
  return np.concatenate([pts[keep].astype(np.float32), refl], 1)
