"""Evaluation metrics against brute-force numpy/scipy computations."""

import numpy as np
import pytest
import scipy.ndimage
from scipy.spatial import cKDTree

from dusty_jax import codec
from dusty_jax.metrics import chamfer, clouds, depth, point_sets, swd


def _cloud_sets(n, m, p, seed=0, shift=0.0):
  rng = np.random.default_rng(seed)
  a = rng.normal(0, 0.2, (n, p, 3)).astype(np.float32)
  b = (rng.normal(0, 0.2, (m, p, 3)) + shift).astype(np.float32)
  return a, b


def _cd_ref(a, b):
  d_ab, _ = cKDTree(b).query(a)
  d_ba, _ = cKDTree(a).query(b)
  return np.mean(d_ab ** 2) + np.mean(d_ba ** 2)


def test_chamfer_matrix_matches_kdtree():
  a, b = _cloud_sets(5, 7, 64)
  got = chamfer.pairwise(a, b, tile=3)
  want = np.array([[_cd_ref(x, y) for y in b] for x in a])
  np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-7)
  sym = chamfer.pairwise(a, tile=2)
  want_sym = np.array([[_cd_ref(x, y) for y in a] for x in a])
  np.testing.assert_allclose(sym, want_sym, rtol=1e-4, atol=1e-6)
  np.testing.assert_array_equal(sym, sym.T)


def test_chamfer_invariant_to_point_and_cloud_order():
  a, b = _cloud_sets(4, 3, 50, seed=1)
  rng = np.random.default_rng(2)
  base = chamfer.pairwise(a, b, tile=2)
  a2 = a[:, rng.permutation(50)]
  perm = rng.permutation(3)
  np.testing.assert_allclose(chamfer.pairwise(a2, b[perm], tile=2), base[:, perm],
                             rtol=1e-5)


def test_chamfer_extremes():
  one = np.zeros((1, 1, 3), np.float32)
  dup = np.zeros((1, 10, 3), np.float32)
  assert chamfer.pairwise(one, dup)[0, 0] == 0
  assert float(chamfer.chamfer(dup[0], dup[0])) == 0
  far = np.full((1, 2, 3), 1.0, np.float32)
  np.testing.assert_allclose(chamfer.pairwise(one, far)[0, 0], 6.0, rtol=1e-6)


def _fps_ref(points, valid, k):
  idx = [int(np.flatnonzero(valid)[0])]
  dist = np.where(valid, np.inf, -np.inf)
  dist[idx[0]] = 0
  for _ in range(k - 1):
    dist = np.minimum(dist, ((points - points[idx[-1]]) ** 2).sum(-1))
    idx.append(int(np.argmax(dist)))
  return np.array(idx)


def test_fps_matches_reference_and_excludes_drops():
  rng = np.random.default_rng(3)
  pts = rng.normal(size=(3, 300, 3)).astype(np.float32)
  valid = rng.uniform(size=(3, 300)) > 0.3
  got = np.asarray(clouds.farthest_point_indices(pts, valid, 32))
  for i in range(3):
    np.testing.assert_array_equal(got[i], _fps_ref(pts[i], valid[i], 32))
    assert valid[i][got[i]].all()
    assert len(set(got[i].tolist())) == 32


def test_fps_few_points_and_empty():
  pts = np.random.default_rng(4).normal(size=(2, 50, 3)).astype(np.float32)
  valid = np.zeros((2, 50), bool)
  valid[0, [5, 9, 30]] = True
  valid[1, :] = True
  only_second = valid.copy()
  only_second[0] = False
  with pytest.raises(ValueError, match=r'clouds \[0\] have no valid point'):
    clouds.farthest_point_sample(pts, only_second, 4)
  out = np.asarray(clouds.farthest_point_sample(pts, valid, 8))
  assert set(map(tuple, out[0].tolist())) == set(map(tuple, pts[0, [5, 9, 30]].tolist()))


def test_mmd_cov_and_1nna_brute_force():
  rng = np.random.default_rng(5)
  d_sr = rng.uniform(size=(6, 4))
  mmd, cov = point_sets.mmd_cov(d_sr)
  assert mmd == pytest.approx(np.mean([min(d_sr[:, j]) for j in range(4)]))
  assert cov == pytest.approx(len({int(np.argmin(r)) for r in d_sr}) / 4)
  a, b = _cloud_sets(6, 5, 40, seed=6)
  d_rr, d_rs, d_ss = chamfer.pairwise(a), chamfer.pairwise(a, b), chamfer.pairwise(b)
  union = np.concatenate([a, b])
  lab = np.array([1] * 6 + [0] * 5)
  correct = 0
  for i in range(11):
    d = [(_cd_ref(union[i], union[j]), j) for j in range(11) if j != i]
    correct += lab[min(d)[1]] == lab[i]
  assert point_sets.one_nna(d_rr, d_rs, d_ss) == pytest.approx(correct / 11)


def test_identical_and_separated_sets():
  a, b = _cloud_sets(6, 6, 40, seed=7, shift=3.0)
  d_aa = chamfer.pairwise(a)
  mmd, cov = point_sets.mmd_cov(d_aa)
  # Zero up to the rounding of the |x|^2 - 2 x.y + |y|^2 expansion.
  assert 0 <= mmd < 1e-7 and cov == 1.0
  assert np.abs(np.diag(d_aa)).max() < 1e-7
  assert point_sets.one_nna(d_aa, chamfer.pairwise(a, b), chamfer.pairwise(b)) == 1.0


def _jsd_ref(sets, res=28):
  ax = np.arange(res) / (res - 1) - 0.5
  grid = np.stack(np.meshgrid(ax, ax, ax, indexing='ij'), -1).reshape(-1, 3)
  grid = grid[np.linalg.norm(grid, axis=1) <= 0.5]
  tree = cKDTree(grid)
  counts = []
  for s in sets:
    _, idx = tree.query(s.reshape(-1, 3) * 0.5)
    counts.append(np.bincount(idx, minlength=len(grid)).astype(float))
  p, q = (c / c.sum() for c in counts)
  h = lambda v: -np.sum(v[v > 0] * np.log2(v[v > 0]))
  return h((p + q) / 2) - (h(p) + h(q)) / 2


def test_jsd_matches_nearest_grid_reference():
  rng = np.random.default_rng(8)
  # Spread over and beyond the sphere so the boundary search is exercised.
  a = rng.uniform(-1.3, 1.3, (4, 500, 3)).astype(np.float32)
  b = rng.normal(0, 0.4, (3, 500, 3)).astype(np.float32)
  assert point_sets.jsd(a, b) == pytest.approx(_jsd_ref([a, b]), rel=1e-5)
  assert point_sets.jsd(a, a[::-1]) == pytest.approx(0.0, abs=1e-12)
  counts = np.asarray(point_sets.occupancy(a))
  assert counts.sum() == a.shape[0] * a.shape[1]


def test_swd_pyramid_matches_scipy_mirror():
  rng = np.random.default_rng(9)
  x = rng.normal(size=(2, 16, 32)).astype(np.float32)
  k = np.outer([1, 4, 6, 4, 1], [1, 4, 6, 4, 1]) / 256.0
  want = scipy.ndimage.convolve(x, k[None], mode='mirror')[:, ::2, ::2]
  np.testing.assert_allclose(swd.pyr_down(x), want, rtol=1e-5, atol=1e-6)
  up = np.zeros((2, 16, 32), np.float32)
  up[:, ::2, ::2] = want
  want_up = scipy.ndimage.convolve(up, 4 * k[None], mode='mirror')
  np.testing.assert_allclose(swd.pyr_up(want), want_up, rtol=1e-5, atol=1e-6)


def test_swd_properties():
  import jax
  rng = np.random.default_rng(10)
  a = rng.normal(size=(16, 32, 64)).astype(np.float32)
  b = rng.normal(size=(16, 32, 64)).astype(np.float32)
  c = scipy.ndimage.gaussian_filter(b, (0, 2, 2)).astype(np.float32)
  key = jax.random.key(0)
  same = swd.swd(key, a, b, per_image=64)
  diff = swd.swd(key, a, c, per_image=64)
  assert set(same) == {'swd_32', 'swd_16', 'swd_mean'}
  # Descriptors are normalised per set, so only structure counts: still clear.
  assert diff['swd_mean'] > 2 * same['swd_mean']
  with pytest.raises(ValueError, match='same number and shape'):
    swd.swd(key, a, b[:3])


def test_depth_errors_against_numpy():
  rng = np.random.default_rng(11)
  t = rng.uniform(1, 80, (2, 8, 16)).astype(np.float32)
  p = (t * rng.uniform(0.7, 1.4, t.shape)).astype(np.float32)
  m = rng.uniform(size=t.shape) > 0.3
  m[1] = False
  got = {k: np.asarray(v) for k, v in depth.depth_errors(p, t, m).items()}
  tt, pp = t[0][m[0]], p[0][m[0]]
  r = np.maximum(pp / tt, tt / pp)
  want = {'abs_rel': np.mean(np.abs(pp - tt) / tt), 'sq_rel': np.mean((pp - tt) ** 2 / tt),
          'rmse': np.sqrt(np.mean((pp - tt) ** 2)),
          'rmse_log': np.sqrt(np.mean((np.log(pp) - np.log(tt)) ** 2)),
          'delta1': np.mean(r < 1.25), 'delta2': np.mean(r < 1.25 ** 2),
          'delta3': np.mean(r < 1.25 ** 3)}
  for k, v in want.items():
    assert got[k][0] == pytest.approx(v, rel=1e-5)
    assert np.isnan(got[k][1])
  assert got['count'].tolist() == [m[0].sum(), 0]


def test_scans_to_clouds_units(tiny):
  d = np.full((1,) + tiny.shape, 60.0, np.float32)
  d[0, 0, 0] = 0
  pts, valid = clouds.scans_to_clouds(codec.encode(d, tiny),
                                      tiny.nominal_angles(), tiny)
  norms = np.linalg.norm(np.asarray(pts), axis=-1)
  np.testing.assert_allclose(norms[np.asarray(valid)], 0.5, rtol=1e-4)
  assert not bool(valid[0, 0])


def test_reliability_and_ece():
  from dusty_jax.metrics import calibration
  rng = np.random.default_rng(12)
  truth = rng.uniform(size=100_000)
  perfect = calibration.reliability(truth, truth, bins=10)
  assert perfect['ece'] < 1e-12 and perfect['count'].sum() == 100_000
  biased = calibration.reliability(np.clip(truth + 0.2, 0, 1), truth, bins=10)
  # Brute force: weighted mean of per-bin |mean pred - mean truth|.
  pred = np.clip(truth + 0.2, 0, 1)
  b = np.minimum((pred * 10).astype(int), 9)
  want = sum((b == i).mean() * abs(pred[b == i].mean() - truth[b == i].mean())
             for i in range(10) if (b == i).any())
  assert biased['ece'] == pytest.approx(want, rel=1e-9)
  assert 0.15 < biased['ece'] < 0.2
  with pytest.raises(ValueError, match='at least one pixel'):
    calibration.reliability(truth, truth, mask=np.zeros_like(truth, bool))


# --- protocol='paper': the authors' computation, checked against small
# independent computations written from its description ----------------------

def _fps_kernel_ref(points, k, threads):
  """The authors' FPS kernel emulated thread by thread: start at index 0;
  each thread walks its strided indices, skipping points with squared norm
  <= 1e-3, keeps its strictly largest running distance (first on ties);
  then a pairwise tree reduction where the lower slot keeps its pick unless
  the upper one is strictly larger."""
  n = len(points)
  temp = np.full(n, 1e10, np.float32)
  mag = (points.astype(np.float32) ** 2).sum(-1)
  idx = [0]
  for _ in range(1, k):
    last = points[idx[-1]]
    best = np.full(threads, -1.0, np.float32)
    besti = np.zeros(threads, np.int64)
    for t in range(threads):
      for j in range(t, n, threads):
        if mag[j] <= 1e-3:
          continue
        d2 = min(np.float32(((points[j] - last) ** 2).sum()), temp[j])
        temp[j] = d2
        if d2 > best[t]:
          best[t], besti[t] = d2, j
    s = threads // 2
    while s >= 1:
      for t in range(s):
        if best[t + s] > best[t]:
          best[t], besti[t] = best[t + s], besti[t + s]
      s //= 2
    idx.append(int(besti[0]))
  return np.array(idx)


def _fps_with_threads(points, k, threads):
  """clouds' paper kernel with another thread count (as for N < 512)."""
  import unittest.mock
  with unittest.mock.patch.object(clouds, 'PAPER_MAX_THREADS', threads):
    clouds._fps_chunk.clear_cache()
    try:
      valid = (points ** 2).sum(-1) > np.float32(clouds.PAPER_MIN_SQUARED_NORM)
      return np.asarray(clouds._fps_chunk(points, valid, k, True))[0]
    finally:
      clouds._fps_chunk.clear_cache()


def test_fps_paper_matches_kernel_emulation():
  rng = np.random.default_rng(20)
  n, k = 96, 40
  pts = (rng.normal(size=(3, n, 3)) * 0.3).astype(np.float32)
  valid = rng.uniform(size=(3, n)) > 0.3
  valid[:, 0] = False  # pixel 0 dropped: the origin is the first sample
  valid[1, 0] = True   # ... except in cloud 1
  pts[:, 5] = [0.01, 0.01, 0.01]  # valid but within 3.79 m: never picked
  valid[:, 5] = True
  for a, b in ((7, 40), (12, 77), (33, 90), (17, 81)):  # exact duplicates:
    pts[:, b] = pts[:, a]                              # ties across threads
    valid[:, [a, b]] = True
  valid[2] = False  # 3 points to pick beyond 3.79 m: the rest are ties at 0
  valid[2, [3, 5, 50, 70]] = True
  zeroed = np.where(valid[..., None], pts, 0.0).astype(np.float32)
  for threads in (8, 32):  # other thread counts, so ties cross threads
    for i in range(3):
      np.testing.assert_array_equal(_fps_with_threads(zeroed[i:i + 1], k, threads),
                                    _fps_kernel_ref(zeroed[i], k, threads))
  got = np.asarray(clouds.farthest_point_indices(zeroed, valid, k, protocol='paper'))
  for i in range(3):
    np.testing.assert_array_equal(got[i], _fps_kernel_ref(zeroed[i], k, 64))
  assert (got[:, 0] == 0).all() and not (got[:, 1:] == 5).any()
  sample = np.asarray(clouds.farthest_point_sample(pts, valid, k, protocol='paper'))
  np.testing.assert_array_equal(sample[0, 0], 0.0)  # the origin, from pixel 0
  np.testing.assert_array_equal(sample[1, 0], pts[1, 0])
  assert set(got[2].tolist()) == {0, 3, 50, 70}
  # The reference protocol starts at the first valid pixel and keeps near points.
  ref = np.asarray(clouds.farthest_point_indices(pts, valid, k))
  assert ref[0, 0] == np.flatnonzero(valid[0])[0] and valid[0][ref[0]].all()
  assert set(ref[2].tolist()) == {3, 5, 50, 70}


def test_fps_paper_thread_count_and_tie_order():
  assert [clouds.paper_threads(n) for n in (1, 2, 3, 100, 512, 1023, 16384)] == \
      [1, 2, 2, 64, 512, 512, 512]
  # 8 threads: slots merge 4 -> 0, 2 -> 0, 1 -> 0, so thread 4 outranks 1.
  order = clouds.paper_tie_order(16)
  assert order.tolist() == [0, 8, 4, 12, 2, 10, 6, 14, 1, 9, 5, 13, 3, 11, 7, 15]


def _jsd_paper_ref(p, q, eps=1e-8):
  """The authors' JSD as described: their entropy adds eps to its argument
  in place, so the mixture is formed from already shifted vectors."""
  def entropy(v):  # mutates v, as theirs does
    v += eps
    return -np.sum(v * np.log2(v))
  p = np.asarray(p, np.float64) / np.sum(p)
  q = np.asarray(q, np.float64) / np.sum(q)
  e_p, e_q = entropy(p), entropy(q)
  return entropy((p + q) / 2) - (e_p + e_q) / 2


def test_jsd_paper_eps_bias():
  p = np.array([3.0, 0, 1, 0, 0, 6])
  q = np.array([0.0, 2, 1, 0, 4, 1])
  got = point_sets.jsd_from_counts(p, q, 'paper')
  assert got == pytest.approx(_jsd_paper_ref(p, q), rel=1e-12)
  assert abs(got - point_sets.jsd_from_counts(p, q)) > 1e-8
  # Identical sets: 0 by the definition, a bias per empty cell in theirs.
  rng = np.random.default_rng(21)
  a = rng.normal(0, 0.3, (4, 300, 3)).astype(np.float32)
  counts = point_sets.occupancy(a)
  empty = int((counts == 0).sum())
  per_cell = -2e-8 - 1e-8 * np.log2(1e-8)
  assert point_sets.jsd(a, a) == pytest.approx(0.0, abs=1e-12)
  bias = point_sets.jsd(a, a, protocol='paper')
  assert bias == pytest.approx(_jsd_paper_ref(counts, counts), rel=1e-9)
  assert bias == pytest.approx(empty * per_cell, rel=0.05)  # + occupied cells
  assert 0.0015 < bias < 0.003
  with pytest.raises(ValueError, match='unknown protocol'):
    point_sets.jsd_from_counts(p, q, 'papers')


def test_swd_paper_pyramid_is_shifted_one_pixel():
  rng = np.random.default_rng(22)
  x = rng.normal(size=(2, 8, 16)).astype(np.float32)
  k = np.outer([1, 4, 6, 4, 1], [1, 4, 6, 4, 1]) / 256.0
  up = np.zeros((2, 16, 32), np.float32)
  up[:, 1::2, 1::2] = x  # the coarse pixels at odd positions
  want = scipy.ndimage.convolve(up, 4 * k[None], mode='mirror')
  np.testing.assert_allclose(swd.pyr_up(x, shifted=True), want, rtol=1e-5, atol=1e-6)
  assert not np.allclose(swd.pyr_up(x, shifted=True), swd.pyr_up(x), atol=1e-3)
  img = rng.normal(size=(2, 32, 64)).astype(np.float32)
  down = scipy.ndimage.convolve(img, k[None], mode='mirror')[:, ::2, ::2]
  up = np.zeros_like(img)
  up[:, 1::2, 1::2] = down
  band = img - scipy.ndimage.convolve(up, 4 * k[None], mode='mirror')
  pyr = swd.laplacian_pyramid(img, 2, shifted=True)
  np.testing.assert_allclose(pyr[0], band, rtol=1e-4, atol=1e-5)
  np.testing.assert_allclose(pyr[1], down, rtol=1e-5, atol=1e-6)


def test_swd_paper_patches_shared_by_the_batch():
  import jax
  b, h, w = 5, 12, 20
  pos = np.arange(h)[:, None] * 100 + np.arange(w)[None]  # value encodes position
  imgs = (pos[None] + 10000 * np.arange(b)[:, None, None]).astype(np.float32)
  centre = lambda p: (p[:, 24].astype(int) % 10000).reshape(b, -1)  # 7x7: element 24
  shared = np.asarray(swd.patches(jax.random.key(0), imgs, 32, 7, shared=True))
  c = centre(shared)
  assert (c == c[0]).all()  # the same positions in every image
  assert len(set(c[0].tolist())) == 32  # drawn without replacement
  assert (c[0] // 100 >= 3).all() and (c[0] // 100 < h - 3).all()
  assert (c[0] % 100 >= 3).all() and (c[0] % 100 < w - 3).all()
  np.testing.assert_array_equal(shared[:32, 0], imgs[0][c[0] // 100 - 3, c[0] % 100 - 3])
  # More patches than windows (6 x 14 here): every window once.
  every = centre(np.asarray(swd.patches(jax.random.key(1), imgs, 500, 7, shared=True)))
  assert every.shape == (b, 84) and len(set(every[0].tolist())) == 84
  own = centre(np.asarray(swd.patches(jax.random.key(0), imgs, 32, 7)))
  assert not (own == own[0]).all()  # reference: positions drawn per image


def test_swd_paper_directions_and_standardisation():
  import jax
  rng = np.random.default_rng(23)
  a = rng.normal(size=(300, 49)).astype(np.float32)
  b = (rng.normal(size=(300, 49)) * 1.5 + 0.2).astype(np.float32)
  key = jax.random.key(3)
  got = float(swd.sliced_wasserstein(key, a, b, 4, 16, paper=True))
  want = []
  for k in jax.random.split(key, 4):
    dirs = np.asarray(jax.random.normal(k, (49, 16)), np.float64)
    dirs /= dirs.std(axis=0, ddof=1)  # the authors' scaling, not the norm
    pa, pb = np.sort(a @ dirs, axis=0), np.sort(b @ dirs, axis=0)
    want.append(np.abs(pa - pb).mean())
  assert got == pytest.approx(np.mean(want), rel=1e-4)
  ratio = got / float(swd.sliced_wasserstein(key, a, b, 4, 16))
  assert 6 < ratio < 8  # about sqrt(49 - 1)
  d = rng.normal(size=(50, 9)).astype(np.float32)
  np.testing.assert_allclose(swd.normalise(d, ddof=1),
                             (d - d.mean()) / (d.std(ddof=1) + 1e-8), rtol=1e-4, atol=1e-5)


def test_swd_paper_end_to_end_scale():
  import jax
  rng = np.random.default_rng(24)
  a = rng.normal(size=(16, 32, 64)).astype(np.float32)
  c = scipy.ndimage.gaussian_filter(rng.normal(size=(16, 32, 64)),
                                    (0, 2, 2)).astype(np.float32)
  key = jax.random.key(0)
  ref = swd.swd(key, a, c, per_image=64)['swd_mean']
  paper = swd.swd(key, a, c, per_image=64, protocol='paper')['swd_mean']
  assert 5 < paper / ref < 10
  # Each part alone: the directions scale by about 7 on the same descriptors.
  only = lambda *p: swd.swd(key, a, c, per_image=64, protocol='paper',
                            paper_parts=p)['swd_mean']
  assert 6.5 < only('directions') / ref < 7.5
  assert only('pyramid') != ref and only('patches') != ref
  with pytest.raises(ValueError, match='unknown parts'):
    only('pyramids')
