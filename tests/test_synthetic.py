"""Simulated data: scenes, the simulated LiDAR (determinism, drop statistics),
the datasets, and the real-data path."""

import os

import numpy as np
import pytest

from dusty_jax import writers
from dusty_jax.data import (arrays, embree, kitti as kitti_io, prepare, scene,
                            simulated_lidar, synthetic)

DATA = os.path.join(os.path.dirname(__file__), 'data')


@pytest.fixture(scope='module')
def scans():
  from dusty_jax.sensor import get_sensor
  sensor = get_sensor('kitti')
  return sensor, [simulated_lidar.render_scan(s, sensor, kind=k)
                  for s, k in enumerate(scene.SCENE_KINDS * 2)]


def test_same_seed_same_scan(kitti):
  a = simulated_lidar.render_scan(7, kitti)
  b = simulated_lidar.render_scan(7, kitti)
  c = simulated_lidar.render_scan(8, kitti)
  np.testing.assert_array_equal(a.depth, b.depth)
  np.testing.assert_array_equal(a.drop_prob, b.drop_prob)
  assert not np.array_equal(a.depth, c.depth)


def test_drop_fraction_plausible(scans):
  _, ss = scans
  fractions = [float(np.mean(s.depth == 0)) for s in ss]
  # Real KITTI drops roughly 10-25% of 64x256 pixels; allow open rural sky.
  assert all(0.05 < f < 0.4 for f in fractions), fractions
  assert 0.1 < np.mean(fractions) < 0.3, fractions


def test_glass_drops_far_more_than_asphalt(scans):
  _, ss = scans
  mat = np.concatenate([s.material.ravel() for s in ss])
  p = np.concatenate([s.drop_prob.ravel() for s in ss])
  obs = np.concatenate([s.depth.ravel() for s in ss])
  glass, asphalt = (mat == scene.MATERIAL_IDS['glass'],
                    mat == scene.MATERIAL_IDS['asphalt'])
  assert p[glass].mean() > 0.8 > 0.4 > p[asphalt].mean()
  assert np.mean(obs[glass] == 0) > 3 * np.mean(obs[asphalt] == 0)


def test_observed_matches_complete_within_noise(scans):
  _, ss = scans
  for s in ss:
    valid = s.depth > 0
    assert (s.complete[valid] > 0).all()
    err = s.depth[valid] - s.complete[valid]
    assert abs(err.mean()) < 3 * simulated_lidar.RANGE_NOISE_M / np.sqrt(valid.sum()) + 1e-3
    assert np.abs(err).max() < 6 * simulated_lidar.RANGE_NOISE_M
    # Drops only where a drop is possible; never a return where p = 1.
    assert not (valid & (s.drop_prob >= 1)).any()
    assert ((s.drop_prob >= 0) & (s.drop_prob <= 1)).all()


def test_sky_and_ego_always_dropped(scans):
  _, ss = scans
  for s in ss:
    certain = (s.material < 0) | (s.material == scene.MATERIAL_IDS['ego'])
    assert (s.drop_prob[certain] == 1).all() and (s.depth[certain] == 0).all()
    assert (s.complete[certain] == 0).all()
  assert any((s.material == scene.MATERIAL_IDS['ego']).any() for s in ss)


def test_bin_unfolds_to_rendered_image_exactly(scans, tmp_path):
  sensor, ss = scans
  for i, s in enumerate(ss):
    path = str(tmp_path / f'{i:06d}.bin')
    kitti_io.write_bin(path, simulated_lidar.to_sensor_order(s.depth, sensor))
    image, report = kitti_io.load_scan(path, sensor)
    np.testing.assert_allclose(image, s.depth, rtol=2e-6)
    assert (image > 0).sum() == (s.depth > 0).sum()


def test_write_dataset_through_prepare(tiny, tmp_path):
  out = str(tmp_path / 'syn')
  meta = synthetic.write_dataset(out, tiny, 4, seed=3,
                                 splits={'train': 4, 'val': 2}, bins=True,
                                 progress=False, workers=2)
  assert meta['splits'] == {'train': 4, 'val': 2}
  obs = arrays.load_split(out, 'train', tiny)
  assert obs.shape == (4, 16, 64)
  comp = arrays.load_split(out, 'train', tiny, 'complete')
  prob = arrays.load_split(out, 'train', tiny, 'drop_prob')
  assert comp.shape == prob.shape == obs.shape
  labels = writers.read_labels(os.path.join(out, 'preview.png'))
  assert labels['panels'][:3] == [f'{t} (training scan 1)' for t in (
      'observed scan', 'complete depth', 'drop probability')]
  assert labels['colour bars'] == [writers.COLOUR_BAR[writers.DEPTH]] * 2 + [
      'probability of a drop']
  # Same scans with one worker (scene seeds do not depend on workers), which
  # the workers wrote into the files themselves (no temporary file is left).
  for want, got in zip(synthetic.simulate(4, tiny, seed=30, progress=False),
                       (obs, comp, prob)):
    np.testing.assert_array_equal(want, got)
  assert not [f for f in os.listdir(out) if 'tmp' in f]
  one = str(tmp_path / 'one')
  synthetic.write_dataset(one, tiny, 2, seed=3, splits={'train': 2}, progress=False, workers=1)
  np.testing.assert_array_equal(arrays.load_split(one, 'train', tiny), obs[:2])
  # The .bin files go through the real KITTI preparation unchanged.
  prepared = str(tmp_path / 'prepared')
  prepare.prepare('kitti', os.path.join(out, 'kitti'), prepared, sensor=tiny,
                  log=lambda m: None)
  np.testing.assert_allclose(arrays.load_split(prepared, 'train', tiny), obs,
                             rtol=2e-6)


def test_fallback_without_embree_agrees(tiny):
  mesh, _, _ = scene.build_scene(1, 'rural')
  d = simulated_lidar.ray_directions(tiny).reshape(-1, 3)[::7]
  o = np.zeros_like(d)
  if not simulated_lidar.has_embree():
    pytest.skip('embreex not installed: only the fallback is available')
  a = simulated_lidar.intersector(mesh, True).intersects_id(
      o, d, multiple_hits=False, return_locations=True)
  b = simulated_lidar.intersector(mesh, False).intersects_id(
      o, d, multiple_hits=False, return_locations=True)
  da, db = np.full(len(d), np.inf), np.full(len(d), np.inf)
  da[a[1]] = np.linalg.norm(a[2], axis=1)
  db[b[1]] = np.linalg.norm(b[2], axis=1)
  np.testing.assert_allclose(da, db, rtol=1e-4)


needs_embree = pytest.mark.skipif(
    not (simulated_lidar.has_embree() and embree.available()),
    reason='embreex (with its Embree 4 library) not installed')


@needs_embree
@pytest.mark.parametrize('seed,kind', [(0, 'urban'), (11, 'residential'), (22, 'rural'),
                                       (2_000_005, None)])
def test_direct_embree_equals_trimesh_embree(seed, kind):
  """The fast ray caster (data/embree.py) against trimesh's Embree intersector,
  which made every cached dataset: every output of a scan, bit for bit."""
  from dusty_jax.sensor import get_sensor
  sensor = get_sensor('kitti')
  fast = simulated_lidar.render_scan(seed, sensor, kind, raycaster='embree')
  plain = simulated_lidar.render_scan(seed, sensor, kind, raycaster='pyembree')
  for name in ('depth', 'complete', 'drop_prob', 'material', 'incidence_cos'):
    a, b = getattr(fast, name), getattr(plain, name)
    assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
  assert (fast.material >= 0).any() and (fast.material < 0).any()  # hits and sky


@needs_embree
def test_direct_embree_first_hits_small_mesh():
  """Misses, a degenerate face, a mesh away from the origin and two faces
  met at a grazing angle: the same (tri, ray, location) as ray_pyembree,
  the hit faces' normals as trimesh's face normals, and face_normals as
  trimesh's (0 where degenerate)."""
  import trimesh
  box = trimesh.creation.box(extents=(2.0, 3.0, 1.0))
  # Faces crossing the y axis at y = 10 and y = -10, tilted 1e-6 and 1e-3
  # from it: ray_pyembree drops the first hit (|cos| <= 1e-5), keeps the other.
  tilted = [[[s * t * -2, s * 8, -1], [s * t * 2, s * 12, -1], [0, s * 10, 1]]
            for s, t in ((1, 1e-6), (-1, 1e-3))]
  v = np.concatenate([box.vertices + [10.0, 1.0, 0.2], [[5, 0, 0], [5, 0, 0], [5, 0, 0]],
                      *tilted])
  f = np.concatenate([box.faces, [[8, 9, 10], [11, 12, 13], [14, 15, 16]]])
  mesh = trimesh.Trimesh(v, f, process=False)  # (face 12 has no area)
  rng = np.random.default_rng(0)
  d = np.concatenate([rng.normal(size=(300, 3)) + [3.0, 0.0, 0.0],
                      [[1.0, 0.07, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0],
                       [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]])
  rays = embree.Rays(d)
  tri, ray, loc, normals = embree.first_hits(mesh.vertices.view(np.ndarray),
                                             mesh.faces.view(np.ndarray), rays)
  ref = simulated_lidar.intersector(mesh, True).intersects_id(
      np.zeros_like(d), d, multiple_hits=False, return_locations=True)
  for a, b in zip((tri, ray, loc), ref):
    assert a.tobytes() == np.asarray(b).tobytes()
  assert 0 < len(ray) < len(d)
  assert normals.tobytes() == mesh.face_normals[tri].tobytes()
  assert len(np.unique(tri)) > 1
  assert len(d) - 2 not in ray and tri[ray == len(d) - 1] == [14]
  every = embree.face_normals(mesh.vertices.view(np.ndarray), mesh.faces.view(np.ndarray))
  assert every.tobytes() == mesh.face_normals.tobytes()
  assert (every[12] == 0).all()


@needs_embree
def test_faces_toward_the_sensor_are_enough():
  """embree.facing_origin drops exactly the faces turned away from the
  origin (trimesh's normals), most of a scene's; Embree given only the rest
  finds the same first hits: the same rays, materials and points."""
  from dusty_jax.sensor import get_sensor
  mesh, material, _ = scene.build_scene(7, 'residential')
  vertices, faces = mesh.vertices.view(np.ndarray), mesh.faces.view(np.ndarray)
  facing = embree.facing_origin(vertices, faces)
  toward = np.einsum('ij,ij->i', mesh.face_normals, vertices[faces[:, 0]])
  clear = np.abs(toward) > 1e-9
  np.testing.assert_array_equal(facing[clear], toward[clear] < 0)
  assert 0.3 < facing.mean() < 0.6
  rays = simulated_lidar._embree_rays(get_sensor('kitti'))
  every = embree.first_hits(vertices, faces, rays)
  some = embree.first_hits(vertices, faces, rays, np.flatnonzero(facing))
  np.testing.assert_array_equal(some[1], every[1])
  np.testing.assert_array_equal(material[some[0]], material[every[0]])
  assert facing[every[0]].all()  # the full scene's first hits face the sensor too
  np.testing.assert_allclose(some[2], every[2], rtol=1e-12, atol=1e-9)
  np.testing.assert_array_equal(some[3], every[3])


def test_scene_builder_equals_parts_one_at_a_time():
  """SceneBuilder transforms parts template by template; each part alone is
  ``template * size @ yaw rotation + center``."""
  b = scene.SceneBuilder()
  parts = [(scene._BOX, (2.0, 1.0, 0.5), (3.0, -1.0, 0.25), 'wall', 0.0),
           (scene._CYL, (0.3, 0.3, 4.0), (1.0, 2.0, 2.0), 'metal', 0.3),
           (scene._BOX, (4.2, 1.8, 0.9), (-7.0, 3.0, 0.7), 'paint', np.pi + 0.02),
           (scene._SPHERE, (3.0, 3.0, 2.4), (0.0, 9.0, 5.0), 'foliage', 0.0),
           (scene._CYL, (0.65, 0.25, 0.65), (5.0, 5.0, 0.33), 'asphalt', -0.04)]
  for t, size, center, material, yaw in parts[:2]:
    b.add(t, size, center, material, yaw)
  b.boxes([[0, 0, 0], [1, 1, 1]], [[0.5, 0.5, 0.5], [2, 2, 3]], 'glass')
  for t, size, center, material, yaw in parts[2:]:
    b.add(t, size, center, material, yaw)
  mesh, material = b.mesh()
  expect_v, expect_f, expect_m, n = [], [], [], 0
  def one(vertices, faces, name):
    nonlocal n
    expect_v.append(vertices)
    expect_f.append(faces + n)
    expect_m.append(np.full(len(faces), scene.MATERIAL_IDS[name]))
    n += len(vertices)
  def part(t, size, center, name, yaw):
    v = t.vertices * np.asarray(size)
    if yaw:
      c, s = np.cos(yaw), np.sin(yaw)
      v = v @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
    one(v + np.asarray(center), t.faces, name)
  for p in parts[:2]:
    part(*p)
  for lo, hi in (([0, 0, 0], [0.5, 0.5, 0.5]), ([1, 1, 1], [2, 2, 3])):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    one(scene._BOX.vertices * (hi - lo) + (lo + hi) / 2, scene._BOX.faces, 'glass')
  for p in parts[2:]:
    part(*p)
  assert np.concatenate(expect_v).tobytes() == mesh.vertices.view(np.ndarray).tobytes()
  np.testing.assert_array_equal(np.concatenate(expect_f), mesh.faces)
  np.testing.assert_array_equal(np.concatenate(expect_m), material)


def test_simulated_data_unchanged(tiny):
  """Simulated caches are keyed by (sensor, num, seed) only, so the scans a
  seed gives must never change. The reference arrays were written by
  ``synthetic.simulate(2, tiny_sensor(16, 64), seed=5)`` with Embree at
  commit 97a8342, before data/synthetic.py was split into scene.py,
  simulated_lidar.py and synthetic.py; here the split reproduced them bit
  for bit. The tolerance only allows for other CPUs' last bits."""
  if not simulated_lidar.has_embree():
    pytest.skip('reference made with Embree; the fallback differs in the last bits')
  ref = np.load(os.path.join(DATA, 'simulated_tiny16x64_seed5.npz'))
  got = synthetic.simulate(2, tiny, seed=5, progress=False)
  for name, a in zip(('observed', 'complete', 'drop_prob'), got):
    np.testing.assert_array_equal(a > 0, ref[name] > 0, err_msg=name)
    np.testing.assert_allclose(a, ref[name], rtol=1e-6, atol=0, err_msg=name)
  # Scan i of dataset seed s is scene s * 1_000_003 + i.
  for i in range(2):
    one = simulated_lidar.render_scan(5 * 1_000_003 + i, tiny)
    np.testing.assert_array_equal(one.depth, got[0][i])
    np.testing.assert_array_equal(one.complete, got[1][i])
    np.testing.assert_array_equal(one.drop_prob, got[2][i])


def test_synthesize_tool(tmp_path, capsys):
  from dusty_jax.sensor import get_sensor
  from dusty_jax.tools import synthesize
  out = str(tmp_path / 'sim')
  synthesize.main(['--num', '2', '--val', '1', '--test', '0', '--out', out,
                   '--workers', '1'])
  assert "{'train': 2, 'val': 1}" in capsys.readouterr().out
  kitti = get_sensor('kitti')
  assert arrays.load_split(out, 'train', kitti).shape == (2,) + kitti.shape
  assert arrays.load_split(out, 'val', kitti, 'drop_prob').shape == (1,) + kitti.shape
  assert not os.path.exists(arrays.split_path(out, 'test'))
  assert os.path.isfile(os.path.join(out, 'preview.png'))
  with pytest.raises(SystemExit, match=r"--sensor=hdl: a sensor preset .*kitti, mpo.* or an existing sensor spec file"):
    synthesize.main(['--num', '2', '--out', out, '--sensor', 'hdl'])
  with pytest.raises(SystemExit, match='preview.png: a file, not a folder; give a folder'):
    synthesize.main(['--num', '2', '--out', os.path.join(out, 'preview.png')])
  with pytest.raises(SystemExit, match='--num=0'):
    synthesize.main(['--num', '0', '--out', out])


@pytest.mark.slow
def test_spawned_workers_import_no_main_module(tiny, tmp_path):
  """With JAX loaded the workers are spawned; they import simulated_lidar,
  not the caller's main module (a trainer's, with JAX; or one read from
  stdin, which a worker could not import): two workers give the scans of one
  process, and the main module's top-level code runs once."""
  import subprocess
  import sys
  code = ('import jax, numpy as np\n'  # JAX loaded: the pool spawns
          'print("main ran", flush=True)\n'
          'if __name__ == "__main__":\n'
          '  import multiprocessing.pool\n'
          '  start = multiprocessing.pool.Pool.__init__\n'
          '  def started(self, *a, **k):\n'
          '    print("pool of", a[0] if a else k.get("processes"), flush=True)\n'
          '    start(self, *a, **k)\n'
          '  multiprocessing.pool.Pool.__init__ = started\n'
          '  from dusty_jax.data import synthetic\n'
          '  from dusty_jax.sensor import tiny_sensor\n'
          '  o, _, _ = synthetic.simulate(20, tiny_sensor(16, 64), seed=5, progress=False,'
          ' workers=2)\n'
          '  np.save("out.npy", o)\n')
  (tmp_path / 'main.py').write_text(code)
  want, _, _ = synthetic.simulate(20, tiny, seed=5, progress=False)
  # The file first: workers that imported it would print again at once; a
  # stdin main they cannot import at all (their pool would respawn them).
  for args in ([sys.executable, 'main.py'], [sys.executable, '-']):
    proc = subprocess.run(args, input=code, text=True, capture_output=True, cwd=tmp_path,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count('main ran') == 1, (args, proc.stdout)
    assert 'pool of 2' in proc.stdout, (args, proc.stdout)
    np.testing.assert_array_equal(np.load(tmp_path / 'out.npy'), want)
    os.remove(tmp_path / 'out.npy')
