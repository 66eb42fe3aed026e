"""Procedural driving scenes for the simulated LiDAR: materials and meshes.

A scene is a triangle mesh (trimesh) built from a seed, with a material per
face: ground and road with lane markings, sidewalks, buildings with glass
windows, walls, parked and moving cars with glass cabins, poles and trees, in
urban, residential and rural variants, optionally with a cross street, and
the ego vehicle's roof rack. Materials carry what the drop model
(simulated_lidar.py) needs: reflectivity, glass, specular paint, foliage.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

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
REFLECTIVITY = np.array([m.reflectivity for m in MATERIALS.values()])
GLASS = np.array([m.glass for m in MATERIALS.values()])
SPECULAR = np.array([m.specular for m in MATERIALS.values()])
FOLIAGE = np.array([m.foliage for m in MATERIALS.values()])
EGO = np.array([m.ego for m in MATERIALS.values()])

SCENE_KINDS = ('urban', 'residential', 'rural')
EXTENT = 140.0  # metres from the sensor that the ground and the roadside reach
LANE_W = 3.5    # metres, a lane's width

# --- Mesh templates ----------------------------------------------------------
class _Template:
  """A unit mesh's vertices and faces as plain arrays (trimesh's
  TrackedArray re-hashes on every operation: most of a scene's build time)."""

  def __init__(self, mesh: trimesh.Trimesh):
    self.vertices = np.array(mesh.vertices, dtype=np.float64)
    self.faces = np.array(mesh.faces, dtype=np.int64)


_BOX = _Template(trimesh.creation.box(extents=(1.0, 1.0, 1.0)))
_CYL = _Template(trimesh.creation.cylinder(radius=0.5, height=1.0, sections=10))
_SPHERE = _Template(trimesh.creation.icosphere(subdivisions=1, radius=0.5))


class SceneBuilder:
  """Accumulates transformed template meshes with a material per face.

  Parts are recorded as they come and transformed together in :meth:`mesh`,
  template by template: each part's vertices are ``template * size``, turned
  by ``yaw`` (a 3x3 matmul), plus ``center``, the same float64 operations on
  the same values as one part at a time.
  """

  def __init__(self):
    self.parts = []  # (template, size, center, yaw) or (vertices, faces)
    self.material, self.material_faces = [], []  # id and face count per part

  def add(self, template: _Template, size, center, material: str, yaw: float = 0.0):
    self.parts.append((template, size, center, yaw))
    self.material.append(MATERIAL_IDS[material])
    self.material_faces.append(len(template.faces))

  def box(self, lo, hi, material, yaw=0.0):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    self.add(_BOX, hi - lo, (lo + hi) / 2, material, yaw)

  def boxes(self, lo, hi, material):
    """Many axis-aligned boxes at once: lo, hi of shape (n, 3)."""
    lo, hi = np.asarray(lo, float).reshape(-1, 3), np.asarray(hi, float).reshape(-1, 3)
    k = len(lo)
    if not k:
      return
    v = _BOX.vertices[None] * (hi - lo)[:, None] + ((lo + hi) / 2)[:, None]
    f = _BOX.faces[None] + (len(_BOX.vertices) * np.arange(k))[:, None, None]
    self.parts.append((v.reshape(-1, 3), f.reshape(-1, 3)))
    self.material.append(MATERIAL_IDS[material])
    self.material_faces.append(k * len(_BOX.faces))

  def mesh(self):
    nv = np.array([len(p[0].vertices) if len(p) == 4 else len(p[0])
                   for p in self.parts])
    nf = np.asarray(self.material_faces)
    v_start = np.concatenate([[0], np.cumsum(nv)])
    f_start = np.concatenate([[0], np.cumsum(nf)])
    vertices = np.empty((v_start[-1], 3), np.float64)
    faces = np.empty((f_start[-1], 3), np.int64)
    groups = {}
    for i, p in enumerate(self.parts):
      if len(p) == 2:
        vertices[v_start[i]:v_start[i + 1]] = p[0]
        faces[f_start[i]:f_start[i + 1]] = p[1] + v_start[i]
      else:
        groups.setdefault((id(p[0]), bool(p[3])), []).append(i)
    for (_, turned), idx in groups.items():
      template = self.parts[idx[0]][0]
      size = np.array([self.parts[i][1] for i in idx], np.float64)
      center = np.array([self.parts[i][2] for i in idx], np.float64)
      v = template.vertices[None] * size[:, None]
      if turned:
        # Scalar cos and sin, as one part at a time took them: numpy's array
        # loops may round differently in the last bit on some CPUs.
        c = np.array([np.cos(self.parts[i][3]) for i in idx])
        s = np.array([np.sin(self.parts[i][3]) for i in idx])
        rot = np.zeros((len(idx), 3, 3))
        rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1] = c, s, -s, c
        rot[:, 2, 2] = 1
        v = np.matmul(v, rot)
      v += center[:, None]
      k = len(template.vertices)
      vertices[(v_start[idx][:, None] + np.arange(k)).ravel()] = v.reshape(-1, 3)
      m = len(template.faces)
      faces[(f_start[idx][:, None] + np.arange(m)).ravel()] = (
          template.faces[None] + v_start[idx][:, None, None]).reshape(-1, 3)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    return mesh, np.repeat(np.asarray(self.material, np.int64), nf)


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


def kind_of(seed: int) -> str:
  """The kind :func:`build_scene` gives scene ``seed`` when it is not told
  one: the first draw of the scene's generator (the simulator records no
  kind; this recovers it from the seed alone)."""
  return SCENE_KINDS[np.random.default_rng(seed).integers(len(SCENE_KINDS))]


@dataclasses.dataclass(frozen=True)
class _Road:
  """The road along x in the sensor's frame: ``lanes`` lanes, its centre
  line at y = -ego_y (the ego car drives in one of the lanes), on the
  ground at z = ``ground``; where ``cross``, a cross street as wide at x =
  ``cross_x``."""
  lanes: int
  ego_y: float
  ground: float
  cross: bool
  cross_x: float

  @property
  def half(self) -> float:
    """Half the road's width."""
    return self.lanes * LANE_W / 2

  def on_cross(self, x0, x1) -> bool:
    """Whether x0..x1 reaches onto the cross street (2 m to spare)."""
    return self.cross and x1 > self.cross_x - self.half - 2 and x0 < self.cross_x + self.half + 2


def build_scene(seed: int, kind: str | None = None, mount_height: float = 1.73,
                cross_street: bool | None = None):
  """(mesh, face_material, info) of one procedural scene around the origin.

  The sensor is at the origin; the ground at z = -mount_height; the road
  runs along x. ``kind`` is urban, residential or rural (random if None).
  """
  rng = np.random.default_rng(seed)
  kind = kind or SCENE_KINDS[rng.integers(len(SCENE_KINDS))]  # kind_of: this draw
  if kind not in SCENE_KINDS:
    raise ValueError(f'unknown scene kind {kind!r}; known: {SCENE_KINDS}')
  b = SceneBuilder()
  # (The order of the parts below is the order of the generator's draws.)
  road = _road(b, kind, -mount_height, cross_street, rng)
  side_w = 0 if kind == 'rural' else rng.uniform(2.0, 4.0)  # sidewalks' width
  for side in (-1, 1):
    _roadside(b, road, kind, side, side_w, rng)
  _traffic(b, road, kind, rng)
  # The ego vehicle: its body lies inside the sensor's blind cone, but the
  # roof rack behind the sensor shadows a rear sector of the lowest beams.
  b.box((-1.2, -0.3, -0.6), (-0.5, 0.3, -0.35), 'ego')
  mesh, material = b.mesh()
  return mesh, material, {'kind': kind, 'cross_street': bool(road.cross),
                          'lanes': road.lanes}


def _road(b: SceneBuilder, kind: str, g: float, cross_street: bool | None, rng) -> _Road:
  """Lays the ground at z = ``g``, the road with its lane markings (the ego
  car in a random lane) and a cross street (drawn where ``cross_street``
  is None)."""
  lanes = 2 if kind == 'rural' else int(rng.integers(2, 5))
  half = lanes * LANE_W / 2
  ego_y = -half + LANE_W / 2 + LANE_W * int(rng.integers(lanes))
  b.box((-EXTENT, -EXTENT, g - 0.5), (EXTENT, EXTENT, g - 0.02), 'ground')
  b.box((-EXTENT, -half - ego_y, g - 0.1), (EXTENT, half - ego_y, g), 'asphalt')
  for k in range(1, lanes):
    y = -half + k * LANE_W - ego_y
    xs = np.arange(-EXTENT, EXTENT, 9.0)
    b.boxes(np.stack([xs, np.full_like(xs, y - 0.07), np.full_like(xs, g)], 1),
            np.stack([xs + 3.0, np.full_like(xs, y + 0.07),
                      np.full_like(xs, g + 0.005)], 1), 'marking')
  cross = cross_street if cross_street is not None else rng.uniform() < 0.35
  cross_x = rng.uniform(12, 45) * rng.choice([-1, 1])
  if cross:
    b.box((cross_x - half, -EXTENT, g - 0.1), (cross_x + half, EXTENT, g), 'asphalt')
  return _Road(lanes, ego_y, g, cross, cross_x)


def _roadside(b: SceneBuilder, road: _Road, kind: str, side: int, side_w: float, rng):
  """One side of the road (``side`` -1 or +1 in y): its sidewalk (none
  where ``side_w`` is 0), the buildings or, rural, the walls along it,
  then its poles, trees and parked cars."""
  g = road.ground
  edge = side * road.half - road.ego_y
  if side_w:
    for x0 in np.arange(-EXTENT, EXTENT, 20.0):
      if not road.on_cross(x0, x0 + 20):
        y0, y1 = sorted((edge, edge + side * side_w))
        b.box((x0, y0, g), (x0 + 20, y1, g + 0.15), 'sidewalk')
  facade = edge + side * (side_w + rng.uniform(0.5, 4.0))
  _frontage(b, road, kind, side, facade, rng)
  for x in np.arange(-EXTENT + rng.uniform(0, 15), EXTENT, rng.uniform(15, 30)):
    if not road.on_cross(x, x):
      y = edge + side * max(side_w - 0.4, 0.6)
      b.add(_CYL, (0.2, 0.2, 7.0), (x, y, g + 3.5), 'metal')  # a pole
  n_trees = {'urban': 6, 'residential': 18, 'rural': 30}[kind]
  for _ in range(n_trees):
    x = rng.uniform(-EXTENT, EXTENT)
    if not road.on_cross(x, x):
      y = edge + side * (side_w + rng.uniform(1.0, 20.0 if kind == 'rural' else 3.0))
      _tree(b, x, y, g, rng)
  n_parked = {'urban': 10, 'residential': 8, 'rural': 1}[kind]
  for _ in range(n_parked):
    x = rng.uniform(-70, 70)
    if abs(x) > 4 and not road.on_cross(x, x):
      _car(b, x, edge - side * 1.1, rng.uniform(-0.05, 0.05), g, rng)


def _frontage(b: SceneBuilder, road: _Road, kind: str, side: int, facade: float, rng):
  """Blocks along one side of the road from end to end, their fronts at y
  = ``facade`` (residential: set back from it), with gaps between them and
  none on the cross street: buildings with windows, or, rural, low walls
  and fences scattered beyond it."""
  g = road.ground
  x = -EXTENT
  while x < EXTENT:
    if kind == 'urban':
      length, height = rng.uniform(15, 40), rng.uniform(8, 30)
    elif kind == 'residential':
      length, height = rng.uniform(8, 15), rng.uniform(4, 8)
    else:
      length, height = rng.uniform(20, 60), rng.uniform(0.8, 2.0)
    gap = rng.uniform(0, 2) if kind == 'urban' else rng.uniform(3, 12)
    if not road.on_cross(x, x + length) and rng.uniform() < (0.95 if kind != 'rural' else 0.5):
      if kind == 'rural':  # low walls and fences
        y0 = facade + side * rng.uniform(0, 6)
        b.box((x, y0 - 0.15, g), (x + length, y0 + 0.15, g + height), 'wall')
      else:
        setback = 0 if kind == 'urban' else rng.uniform(2, 8)
        _building(b, x, x + length, facade + side * setback, side,
                  rng.uniform(8, 15), height, g, rng)
    x += length + gap


def _traffic(b: SceneBuilder, road: _Road, kind: str, rng):
  """Cars moving in the road's lanes, each lane's way (none on the ego car)."""
  for _ in range({'urban': 8, 'residential': 4, 'rural': 3}[kind]):
    lane = int(rng.integers(road.lanes))
    y = -road.half + LANE_W / 2 + lane * LANE_W - road.ego_y
    x = rng.uniform(-60, 60)
    if abs(y) < 1 and abs(x) < 8:
      continue
    _car(b, x, y, np.pi * (lane < road.lanes / 2) + rng.uniform(-0.03, 0.03), road.ground, rng)
