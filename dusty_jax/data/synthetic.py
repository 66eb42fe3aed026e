"""A simulated LiDAR on procedural driving scenes: the embedded default data.

Scenes are triangle meshes (trimesh) built from a seed: ground and road with
lane markings, sidewalks, buildings with glass windows, walls, parked and
moving cars with glass cabins, poles and trees, in urban, residential and
rural variants, optionally with a cross street. The sensor sits
``sensor.mount_height`` above the road on the ego car, and casts one ray per
pixel of the range image at the sensor's nominal angles (Embree through
``embreex`` when installed, trimesh's pure-numpy intersector otherwise).

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
import os
import sys

import numpy as np
import trimesh
import tqdm

from dusty_jax.data import arrays, kitti
from dusty_jax.sensor import SensorSpec

# --- Drop model constants ----------------------------------------------------
R0 = 30.0             # reference range of the energy model (m).
E_MIN = 0.02          # signal at which detection probability is 1 - 1/e.
GLASS_FACTOR = 0.12   # share of returns from glass.
FOLIAGE_FACTOR = 0.7  # share of returns from a canopy.
RANDOM_DROPOUT = 0.01
RANGE_NOISE_M = 0.02  # 1-sigma range noise (m).


@dataclasses.dataclass(frozen=True)
class Material:
  reflectivity: float
  glass: bool = False
  specular: float = 0.0
  foliage: bool = False
  ego: bool = False


MATERIALS = {
    'ground': Material(0.25),
    'asphalt': Material(0.12),
    'marking': Material(0.6),
    'sidewalk': Material(0.3),
    'wall': Material(0.45),
    'glass': Material(0.05, glass=True),
    'paint': Material(0.35, specular=0.9),
    'metal': Material(0.5, specular=0.5),
    'bark': Material(0.3),
    'foliage': Material(0.4, foliage=True),
    'ego': Material(0.0, ego=True),
}
MATERIAL_IDS = {name: i for i, name in enumerate(MATERIALS)}
_REFL = np.array([m.reflectivity for m in MATERIALS.values()])
_GLASS = np.array([m.glass for m in MATERIALS.values()])
_SPEC = np.array([m.specular for m in MATERIALS.values()])
_FOLIAGE = np.array([m.foliage for m in MATERIALS.values()])
_EGO = np.array([m.ego for m in MATERIALS.values()])

SCENE_KINDS = ('urban', 'residential', 'rural')

# --- Mesh templates ----------------------------------------------------------
_BOX = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
_CYL = trimesh.creation.cylinder(radius=0.5, height=1.0, sections=10)
_SPHERE = trimesh.creation.icosphere(subdivisions=1, radius=0.5)


class SceneBuilder:
  """Accumulates transformed template meshes with a material per face."""

  def __init__(self):
    self.vertices, self.faces, self.material = [], [], []
    self.n = 0

  def add(self, template, size, center, material: str, yaw: float = 0.0):
    v = template.vertices * np.asarray(size, np.float64)
    if yaw:
      c, s = np.cos(yaw), np.sin(yaw)
      v = v @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
    self.vertices.append(v + np.asarray(center, np.float64))
    self.faces.append(template.faces + self.n)
    self.material.append(np.full(len(template.faces), MATERIAL_IDS[material]))
    self.n += len(template.vertices)

  def box(self, lo, hi, material, yaw=0.0):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    self.add(_BOX, hi - lo, (lo + hi) / 2, material, yaw)

  def boxes(self, lo, hi, material):
    """Many axis-aligned boxes at once: lo, hi of shape (n, 3)."""
    lo, hi = np.asarray(lo, float).reshape(-1, 3), np.asarray(hi, float).reshape(-1, 3)
    k = len(lo)
    if not k:
      return
    nv = len(_BOX.vertices)
    v = _BOX.vertices[None] * (hi - lo)[:, None] + ((lo + hi) / 2)[:, None]
    f = _BOX.faces[None] + (self.n + nv * np.arange(k))[:, None, None]
    self.vertices.append(v.reshape(-1, 3))
    self.faces.append(f.reshape(-1, 3))
    self.material.append(np.full(k * len(_BOX.faces), MATERIAL_IDS[material]))
    self.n += k * nv

  def mesh(self):
    mesh = trimesh.Trimesh(np.concatenate(self.vertices),
                           np.concatenate(self.faces), process=False)
    return mesh, np.concatenate(self.material)


def _car(b: SceneBuilder, x, y, yaw, ground, rng):
  length, width = rng.uniform(3.8, 4.9), rng.uniform(1.7, 1.95)
  body_h = rng.uniform(0.75, 0.95)
  c, s = np.cos(yaw), np.sin(yaw)
  b.add(_BOX, (length, width, body_h), (x, y, ground + 0.3 + body_h / 2),
        'paint', yaw)
  cab_len = length * rng.uniform(0.45, 0.6)
  b.add(_BOX, (cab_len, width * 0.9, 0.55),
        (x - 0.1 * length * c, y - 0.1 * length * s,
         ground + 0.3 + body_h + 0.27), 'glass', yaw)
  for dx in (-0.33, 0.33):  # wheels (dark rubber: low reflectivity paint)
    for dy in (-0.45, 0.45):
      b.add(_CYL, (0.65, 0.25, 0.65),
            (x + dx * length * c - dy * width * s,
             y + dx * length * s + dy * width * c, ground + 0.33), 'asphalt')


def _tree(b: SceneBuilder, x, y, ground, rng):
  h = rng.uniform(2.0, 4.0)
  r = rng.uniform(1.5, 3.0)
  b.add(_CYL, (0.35, 0.35, h), (x, y, ground + h / 2), 'bark')
  b.add(_SPHERE, (2 * r, 2 * r, 1.6 * r), (x, y, ground + h + 0.6 * r), 'foliage')


def _building(b: SceneBuilder, x0, x1, y_face, side, depth, height, ground, rng,
              windows=True):
  """A block from x0 to x1 whose facade is at y_face, extending away."""
  y_far = y_face + side * depth
  b.box((x0, min(y_face, y_far), ground), (x1, max(y_face, y_far), ground + height),
        'wall')
  if not windows:
    return
  xs = np.arange(x0 + 1.0, x1 - 1.5, rng.uniform(2.2, 3.5))
  zs = ground + 0.9 + 3.0 * np.arange(int(height // 3.0))
  wx, wz = [a.ravel() for a in np.meshgrid(xs, zs)]
  keep = rng.uniform(size=wx.shape) < 0.85
  wx, wz = wx[keep], wz[keep]
  yy = np.full_like(wx, y_face - side * 0.02)
  b.boxes(np.stack([wx, yy - 0.03, wz], 1),
          np.stack([wx + 1.3, yy + 0.03, wz + 1.5], 1), 'glass')


def build_scene(seed: int, kind: str | None = None, mount_height: float = 1.73,
                cross_street: bool | None = None):
  """(mesh, face_material, info) of one procedural scene around the origin.

  The sensor is at the origin; the ground at z = -mount_height; the road
  runs along x. ``kind`` is urban, residential or rural (random if None).
  """
  rng = np.random.default_rng(seed)
  kind = kind or SCENE_KINDS[rng.integers(len(SCENE_KINDS))]
  if kind not in SCENE_KINDS:
    raise ValueError(f'unknown scene kind {kind!r}; known: {SCENE_KINDS}')
  g = -mount_height
  extent = 140.0
  b = SceneBuilder()
  lanes = 2 if kind == 'rural' else int(rng.integers(2, 5))
  lane_w = 3.5
  half = lanes * lane_w / 2
  ego_y = -half + lane_w / 2 + lane_w * int(rng.integers(lanes))
  # Ground, road, markings (road frame: centre line at y = 0, ego offset).
  b.box((-extent, -extent, g - 0.5), (extent, extent, g - 0.02), 'ground')
  b.box((-extent, -half - ego_y, g - 0.1), (extent, half - ego_y, g), 'asphalt')
  for k in range(1, lanes):
    y = -half + k * lane_w - ego_y
    xs = np.arange(-extent, extent, 9.0)
    b.boxes(np.stack([xs, np.full_like(xs, y - 0.07), np.full_like(xs, g)], 1),
            np.stack([xs + 3.0, np.full_like(xs, y + 0.07),
                      np.full_like(xs, g + 0.005)], 1), 'marking')
  cross = cross_street if cross_street is not None else rng.uniform() < 0.35
  cross_x = rng.uniform(12, 45) * rng.choice([-1, 1])
  cross_half = lanes * lane_w / 2
  if cross:
    b.box((cross_x - cross_half, -extent, g - 0.1),
          (cross_x + cross_half, extent, g), 'asphalt')

  def on_cross(x0, x1):
    return cross and x1 > cross_x - cross_half - 2 and x0 < cross_x + cross_half + 2

  side_w = 0 if kind == 'rural' else rng.uniform(2.0, 4.0)
  for side in (-1, 1):
    edge = side * half - ego_y
    if side_w:
      for x0 in np.arange(-extent, extent, 20.0):
        if not on_cross(x0, x0 + 20):
          y0, y1 = sorted((edge, edge + side * side_w))
          b.box((x0, y0, g), (x0 + 20, y1, g + 0.15), 'sidewalk')
    facade = edge + side * (side_w + rng.uniform(0.5, 4.0))
    x = -extent
    while x < extent:
      if kind == 'urban':
        length, height = rng.uniform(15, 40), rng.uniform(8, 30)
      elif kind == 'residential':
        length, height = rng.uniform(8, 15), rng.uniform(4, 8)
      else:
        length, height = rng.uniform(20, 60), rng.uniform(0.8, 2.0)
      gap = rng.uniform(0, 2) if kind == 'urban' else rng.uniform(3, 12)
      if not on_cross(x, x + length) and rng.uniform() < (0.95 if kind != 'rural' else 0.5):
        if kind == 'rural':  # low walls and fences
          y0 = facade + side * rng.uniform(0, 6)
          b.box((x, y0 - 0.15, g), (x + length, y0 + 0.15, g + height), 'wall')
        else:
          setback = 0 if kind == 'urban' else rng.uniform(2, 8)
          _building(b, x, x + length, facade + side * setback, side,
                    rng.uniform(8, 15), height, g, rng)
      x += length + gap
    # Poles, trees, parked cars along this side.
    for x in np.arange(-extent + rng.uniform(0, 15), extent, rng.uniform(15, 30)):
      if not on_cross(x, x):
        y = edge + side * max(side_w - 0.4, 0.6)
        b.add(_CYL, (0.2, 0.2, 7.0), (x, y, g + 3.5), 'metal')
    n_trees = {'urban': 6, 'residential': 18, 'rural': 30}[kind]
    for _ in range(n_trees):
      x = rng.uniform(-extent, extent)
      if not on_cross(x, x):
        y = edge + side * (side_w + rng.uniform(1.0, 20.0 if kind == 'rural' else 3.0))
        _tree(b, x, y, g, rng)
    n_parked = {'urban': 10, 'residential': 8, 'rural': 1}[kind]
    for _ in range(n_parked):
      x = rng.uniform(-70, 70)
      if abs(x) > 4 and not on_cross(x, x):
        _car(b, x, edge - side * 1.1, rng.uniform(-0.05, 0.05), g, rng)
  # Moving cars in the lanes (not on the ego car).
  for _ in range({'urban': 8, 'residential': 4, 'rural': 3}[kind]):
    lane = int(rng.integers(lanes))
    y = -half + lane_w / 2 + lane * lane_w - ego_y
    x = rng.uniform(-60, 60)
    if abs(y) < 1 and abs(x) < 8:
      continue
    _car(b, x, y, np.pi * (lane < lanes / 2) + rng.uniform(-0.03, 0.03), g, rng)
  # The ego vehicle: its body lies inside the sensor's blind cone, but the
  # roof rack behind the sensor shadows a rear sector of the lowest beams.
  b.box((-1.2, -0.3, -0.6), (-0.5, 0.3, -0.35), 'ego')
  mesh, material = b.mesh()
  return mesh, material, {'kind': kind, 'cross_street': bool(cross),
                          'lanes': lanes}


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
      rng_dist <= sensor.min_depth) | _EGO[mat]
  r = np.maximum(rng_dist, 1e-3)
  energy = _REFL[mat] * cos_inc * (R0 / r) ** 2
  p_det = 1.0 - np.exp(-energy / E_MIN)
  p_det *= np.where(_GLASS[mat], GLASS_FACTOR, 1.0)
  p_det *= 1.0 - _SPEC[mat] * (1.0 - cos_inc) ** 4
  p_det *= np.where(_FOLIAGE[mat], FOLIAGE_FACTOR, 1.0)
  p_det *= 1.0 - RANDOM_DROPOUT
  return np.where(geometric, 1.0, 1.0 - p_det)


def render_scan(seed: int, sensor: SensorSpec, kind: str | None = None,
                use_embree: bool | None = None) -> Scan:
  """Builds scene ``seed`` and simulates one scan of it."""
  mesh, material, info = build_scene(seed, kind, sensor.mount_height)
  dirs = ray_directions(sensor).reshape(-1, 3)
  origins = np.zeros_like(dirs)
  tri, ray, loc = intersector(mesh, use_embree).intersects_id(
      origins, dirs, multiple_hits=False, return_locations=True)
  n = len(dirs)
  dist = np.full(n, np.inf)
  mat = np.full(n, -1, np.int64)
  cos_inc = np.zeros(n)
  dist[ray] = np.linalg.norm(loc, axis=1)
  mat[ray] = material[tri]
  cos_inc[ray] = np.abs(np.einsum('ij,ij->i', mesh.face_normals[tri], dirs[ray]))
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


def _render_arrays(args):
  seed, sensor = args
  s = render_scan(seed, sensor)
  return s.depth, s.complete, s.drop_prob


def simulate(num: int, sensor: SensorSpec, seed: int = 0, progress: bool = True,
             desc: str = 'simulating', workers: int = 1):
  """(observed, complete, drop_prob) arrays of ``num`` scans, (N, H, W) each.

  Scan i uses scene seed ``seed * 1_000_003 + i``: the result does not depend
  on ``workers``.
  """
  shape = (num,) + sensor.shape
  out = [np.zeros(shape, np.float32) for _ in range(3)]
  jobs = [(seed * 1_000_003 + i, sensor) for i in range(num)]
  bar = tqdm.tqdm(total=num, desc=desc, unit='scan', file=sys.stderr,
                  disable=not progress)
  if workers > 1 and num > 1:
    import multiprocessing
    # Forking a process that runs JAX's threads can deadlock: spawn then.
    method = 'spawn' if 'jax' in sys.modules else 'fork'
    with multiprocessing.get_context(method).Pool(workers) as pool:
      results = pool.imap(_render_arrays, jobs, chunksize=16)
      for i, r in enumerate(results):
        out[0][i], out[1][i], out[2][i] = r
        bar.update()
  else:
    for i, job in enumerate(jobs):
      out[0][i], out[1][i], out[2][i] = _render_arrays(job)
      bar.update()
  bar.close()
  return tuple(out)


SPLIT_SEED_OFFSET = {'train': 0, 'val': 1, 'test': 2}


def write_dataset(out: str, sensor: SensorSpec, num: int, seed: int = 0,
                  splits: dict | None = None, bins: bool = False,
                  progress: bool = True, workers: int = 1) -> dict:
  """Simulates a prepared dataset (see data/arrays.py) with ground truth.

  ``splits`` maps split name to size (default: ``num`` train, num // 10 val
  and test). With ``bins``, every scan is also written as a KITTI ``.bin``
  in sensor order under ``out/kitti/sequences/NN/velodyne`` (train 00, val
  08, test 11) so the real-data path can be exercised on it.
  """
  splits = splits or {'train': num, 'val': max(num // 10, 1),
                      'test': max(num // 10, 1)}
  os.makedirs(out, exist_ok=True)
  seq = {'train': 0, 'val': 8, 'test': 11}
  for split, n in splits.items():
    obs, complete, prob = simulate(
        n, sensor, seed=seed * 10 + SPLIT_SEED_OFFSET[split], progress=progress,
        desc=split, workers=workers)
    arrays.save_array(arrays.split_path(out, split), obs)
    arrays.save_array(arrays.split_path(out, split, 'complete'), complete)
    arrays.save_array(arrays.split_path(out, split, 'drop_prob'), prob)
    if bins:
      for i, d in enumerate(obs):
        kitti.write_bin(os.path.join(out, 'kitti', 'sequences',
                                     f'{seq[split]:02d}', 'velodyne',
                                     f'{i:06d}.bin'), to_sensor_order(d, sensor))
  arrays.save_array(os.path.join(out, arrays.ANGLES), sensor.nominal_angles())
  save_preview(os.path.join(out, 'preview.png'), out, sensor)
  meta = {'dataset': 'synthetic', 'sensor': sensor.name,
          'shape': list(sensor.shape), 'seed': seed,
          'splits': {k: int(v) for k, v in splits.items()}}
  arrays.write_meta(out, meta)
  return meta


def save_preview(path: str, directory: str, sensor: SensorSpec, num: int = 4):
  """PNG of observed depth, complete depth and drop probability, per scan."""
  from dusty_jax import codec, writers
  obs = arrays.load_split(directory, 'train', sensor)[:num]
  comp = arrays.load_split(directory, 'train', sensor, 'complete')[:num]
  prob = arrays.load_split(directory, 'train', sensor, 'drop_prob')[:num]
  rows = []
  for o, c, p in zip(obs, comp, prob):
    rows.append([writers.inv_depth_tile(np.asarray(codec.encode(o, sensor)))])
    rows.append([writers.inv_depth_tile(np.asarray(codec.encode(c, sensor)))])
    rows.append([writers.prob_tile(p)])
  writers.save_grid(path, rows, scale=2)
