"""Initial points and Gaussians: train-view triangulation (DAT-11), PLY files (DAT-12), and
3DGS create_from_pcd (DAT-13, DAT-14)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import data_root

from refgs.constants import SH_C0
from refgs.data.init import INIT_OPACITY, MIN_DIST2, init_gaussians_from_points, knn_log_scales
from refgs.data.pointcloud import read_ply, write_ply
from refgs.errors import ConfigError, SceneError

DATA = data_root()  # $REFGS_DATA or <repo>/../shared/data
FERN = DATA / "fern"
needs_data = pytest.mark.skipif(not (FERN / "sparse" / "0").is_dir(),
                                reason="shared data not available")


def brute_force_log_scales(points):
    d2 = ((points[:, None, :] - points[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    k = min(3, len(points) - 1)
    mean = np.sort(d2, axis=1)[:, :k].mean(1)
    return 0.5 * np.log(np.maximum(mean, MIN_DIST2))


# --------------------------------------------------------------------------------------------
# DAT-13 / DAT-14: create_from_pcd
# --------------------------------------------------------------------------------------------

def test_init_matches_create_from_pcd():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3))
    rgb = rng.uniform(size=(50, 3))
    g = init_gaussians_from_points(pts, rgb)
    assert len(g) == 50 and g.dtype == np.float64
    np.testing.assert_array_equal(g.means, pts)
    assert g.sh.shape == (50, 16, 3)
    np.testing.assert_allclose(g.sh[:, 0], (rgb - 0.5) / SH_C0, rtol=1e-15)
    assert not g.sh[:, 1:].any()
    # the DC term alone reproduces the colour: SH_C0 * dc + 0.5 (CNV-10)
    np.testing.assert_allclose(SH_C0 * g.sh[:, 0] + 0.5, rgb, atol=1e-15)
    np.testing.assert_array_equal(g.quats, np.tile([1.0, 0, 0, 0], (50, 1)))
    np.testing.assert_allclose(g.opacity_logits, np.log(0.1 / 0.9), rtol=1e-15)
    np.testing.assert_allclose(1 / (1 + np.exp(-g.opacity_logits)), INIT_OPACITY, rtol=1e-15)
    np.testing.assert_allclose(g.opacity_logits[0], -2.1972245773362196, rtol=1e-15)
    np.testing.assert_allclose(g.log_scales, np.repeat(brute_force_log_scales(pts)[:, None], 3, 1),
                               rtol=1e-12)


def test_knn_scales_on_a_unit_cube():
    # every corner of the unit cube has exactly three neighbours at distance 1 -> log(1) = 0
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    np.testing.assert_allclose(knn_log_scales(cube), 0.0, atol=1e-15)
    np.testing.assert_allclose(knn_log_scales(3 * cube), np.log(3.0), rtol=1e-15)


def test_knn_scales_match_brute_force_with_clusters():
    rng = np.random.default_rng(1)
    pts = np.concatenate([rng.normal(size=(200, 3)), rng.normal(scale=1e-3, size=(30, 3)) + 5])
    np.testing.assert_allclose(knn_log_scales(pts), brute_force_log_scales(pts), rtol=1e-12)


def test_coincident_points_get_the_floor():
    pts = np.zeros((5, 3))
    np.testing.assert_allclose(knn_log_scales(pts), 0.5 * np.log(1e-7), rtol=1e-15)
    assert abs(0.5 * np.log(MIN_DIST2) - (-8.059047825479161)) < 1e-12


@pytest.mark.parametrize("n", [0, 1, 2, 3])
def test_fewer_than_four_points(n):
    pts = np.array([[0, 0, 0], [2, 0, 0], [0, 4, 0]], float)[:n]
    expect = {0: [], 1: [0.5 * np.log(1e-7)],
              2: [np.log(2.0), np.log(2.0)],                         # one neighbour each
              3: 0.5 * np.log([(4 + 16) / 2, (4 + 20) / 2, (16 + 20) / 2])}[n]
    np.testing.assert_allclose(knn_log_scales(pts), expect, rtol=1e-15)
    g = init_gaussians_from_points(pts, np.full((n, 3), 0.5))
    assert len(g) == n and g.log_scales.shape == (n, 3)
    assert np.all(np.isfinite(g.log_scales))


def test_dtype_and_sh_degree():
    pts = np.random.default_rng(2).normal(size=(10, 3))
    g = init_gaussians_from_points(pts, np.zeros((10, 3)), sh_degree=1, dtype=np.float32)
    assert g.sh.shape == (10, 4, 3)
    assert all(getattr(g, f).dtype == np.float32 for f in g.FIELDS)
    np.testing.assert_allclose(g.sh[:, 0], -0.5 / SH_C0, rtol=1e-6)


@pytest.mark.parametrize("pts, rgb, match", [
    (np.zeros((4, 2)), np.zeros((4, 2)), "points"),
    (np.zeros((4, 3)), np.zeros((3, 3)), "colours"),
    (np.zeros((4, 3)), np.full((4, 3), 255.0), r"\[0, 1\]"),
    (np.full((4, 3), np.nan), np.zeros((4, 3)), "finite"),
])
def test_bad_init_input(pts, rgb, match):
    with pytest.raises(ConfigError, match=match):
        init_gaussians_from_points(pts, rgb)


def test_bad_sh_degree():
    with pytest.raises(ConfigError, match="--sh-degree"):
        init_gaussians_from_points(np.zeros((4, 3)), np.zeros((4, 3)), sh_degree=4)


# --------------------------------------------------------------------------------------------
# DAT-12: PLY
# --------------------------------------------------------------------------------------------

def test_ply_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(20, 3))
    rgb = rng.integers(0, 256, size=(20, 3)) / 255.0
    path = write_ply(tmp_path / "sub" / "points.ply", pts, rgb)
    assert sorted(p.name for p in path.parent.iterdir()) == ["points.ply"]  # no temp left
    p2, c2 = read_ply(path)
    np.testing.assert_array_equal(p2, pts)
    np.testing.assert_allclose(c2, rgb, rtol=1e-15)


def test_ply_errors(tmp_path):
    from plyfile import PlyData, PlyElement

    with pytest.raises(SceneError, match=r"missing\.ply: point cloud file not found"):
        read_ply(tmp_path / "missing.ply")
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"hello")
    with pytest.raises(SceneError, match=r"junk\.ply: not a readable PLY"):
        read_ply(junk)
    rows = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    bare = tmp_path / "bare.ply"
    PlyData([PlyElement.describe(rows, "vertex")]).write(str(bare))
    with pytest.raises(SceneError, match=r"bare\.ply: vertex element lacks red, green, blue"):
        read_ply(bare)


# --------------------------------------------------------------------------------------------
# DAT-11: triangulation from the training views
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def fern():
    from refgs.data import load_scene

    if not (FERN / "sparse" / "0").is_dir():
        pytest.skip("shared data not available")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_scene(FERN)


FERN_3 = [1, 10, 19]  # DAT-10 split of fern, 3 views (tests/test_split.py)


def check_plausible(scene, points, colors, lo, hi):
    from scipy.spatial import cKDTree

    assert lo <= len(points) <= hi
    assert points.shape == colors.shape and points.dtype == np.float64
    assert 0 <= colors.min() and colors.max() <= 1
    for i in FERN_3:  # in front of every training camera, at fern's depths (about 17-78)
        cam = scene.cameras[i]
        z = (points @ cam.rotation.T + cam.translation)[:, 2]
        assert z.min() > 1.0 and 20 < np.median(z) < 45
    # close to the all-view SfM points (median nearest-neighbour spacing there: 0.15)
    dist, _ = cKDTree(scene.points).query(points)
    assert np.median(dist) < 0.5


@needs_data
def test_triangulation_default_preset_fern_3_views(fern, tmp_path):
    from refgs.data.triangulate import triangulate_train_views

    p1, c1 = triangulate_train_views(fern, FERN_3, tmp_path, options="default", seed=0)
    check_plausible(fern, p1, c1, 60, 200)  # measured 104 (docs/spec/data.md)
    p2, c2 = triangulate_train_views(fern, FERN_3, tmp_path, options="default", seed=0)
    np.testing.assert_array_equal(p1, p2)
    np.testing.assert_array_equal(c1, c2)
    assert list(tmp_path.iterdir()) == []  # intermediate files removed


@needs_data
@pytest.mark.slow
def test_triangulation_tuned_preset_fern_3_views(fern, tmp_path):
    from refgs.data.triangulate import triangulate_train_views

    p1, c1 = triangulate_train_views(fern, FERN_3, tmp_path, seed=0)
    check_plausible(fern, p1, c1, 600, 2000)  # measured 1031
    p2, c2 = triangulate_train_views(fern, FERN_3, tmp_path, seed=0)
    np.testing.assert_array_equal(p1, p2)
    np.testing.assert_array_equal(c1, c2)


@needs_data
def test_triangulation_option_errors(fern, tmp_path):
    from refgs.data.triangulate import triangulate_train_views

    with pytest.raises(ConfigError, match="--triangulation"):
        triangulate_train_views(fern, FERN_3, tmp_path, options="best")
    with pytest.raises(ConfigError, match="at least 2"):
        triangulate_train_views(fern, [3], tmp_path)
    bad = {"extraction": {"no_such_option": 1}, "matching": {}, "triangulation": {}}
    with pytest.raises(ConfigError, match="no_such_option"):
        triangulate_train_views(fern, FERN_3, tmp_path, options=bad)
