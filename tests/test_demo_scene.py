"""The self-made demo scene (DAT-15): rendered room corner -> pycolmap SfM -> loadable scene."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from refgs.data import demo, load_scene
from refgs.data.demo import demo_cameras, demo_scene_path, make_demo_scene
from refgs.errors import ConfigError

FILES = ["images/view_000.png", "images/view_011.png", "ground_truth.npz",
         "sparse/0/cameras.bin", "sparse/0/images.bin", "sparse/0/points3D.bin"]


@pytest.fixture(scope="module")
def cached(tmp_path_factory):
    """demo_scene_path() with REFGS_CACHE pointing at a fresh folder (first use builds it)."""
    root = tmp_path_factory.mktemp("cache")
    mp = pytest.MonkeyPatch()
    mp.setenv("REFGS_CACHE", str(root))
    try:
        yield root, demo_scene_path()
    finally:
        mp.undo()


def umeyama(src, dst):
    """Similarity (s, R, t) minimising |s R src + t - dst|^2 (Umeyama 1991)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    e = np.eye(3)
    e[2, 2] = np.sign(np.linalg.det(u @ vt))
    R = u @ e @ vt
    s = np.trace(np.diag(d) @ e) / (a ** 2).sum(1).mean()
    return s, R, md - s * R @ ms


def test_cache_builds_once_atomically(cached, monkeypatch):
    root, path = cached
    assert path == root / f"demo-v{demo.DEMO_VERSION}-{demo.DEMO_WIDTH}x{demo.DEMO_HEIGHT}"
    assert sorted(p.name for p in root.iterdir()) == [path.name]  # no temp folders left
    assert not (path / "sfm").exists() and not list(path.rglob("*.db"))
    monkeypatch.setattr(demo, "make_demo_scene", lambda *a, **k: pytest.fail("rebuilt"))
    assert demo_scene_path() == path


def test_demo_loads_with_sfm_poses_close_to_truth(cached):
    _, path = cached
    scene = load_scene(path, images="images")
    assert len(scene) == 12
    assert scene.names == [f"view_{k:03d}.png" for k in range(12)]
    assert all(im.shape == (120, 160, 3) for im in scene.images)
    assert all((c.width, c.height) == (160, 120) for c in scene.cameras)
    assert 150 <= len(scene.points) <= 5000  # measured 351
    gt = np.load(path / "ground_truth.npz", allow_pickle=False)
    true_centres = np.array([-w[:3, :3].T @ w[:3, 3] for w in gt["world_to_camera"]])
    sfm_centres = np.array([c.center for c in scene.cameras])
    s, R, t = umeyama(sfm_centres, true_centres)
    err = np.linalg.norm(s * sfm_centres @ R.T + t - true_centres, axis=1)
    # cameras sit 3.2 from the target, neighbours ~0.4 apart (a shuffled correspondence gives
    # ~0.15); SfM at 160x120 measured 0.011 and focal within 0.6 %
    assert err.max() < 0.05
    fx_true = gt["K"][0, 0]
    assert abs(scene.cameras[0].fx / fx_true - 1) < 0.05


def test_same_seed_same_files(cached, tmp_path):
    _, path = cached
    again = make_demo_scene(tmp_path / "again", seed=0)
    for f in FILES:
        assert (again / f).read_bytes() == (path / f).read_bytes(), f


def test_seed_moves_the_cameras():
    a = demo_cameras(4, 64, 48, np.random.default_rng(0))
    b = demo_cameras(4, 64, 48, np.random.default_rng(1))
    c = demo_cameras(4, 64, 48, np.random.default_rng(0))
    assert not np.allclose(a[1].world_to_camera, b[1].world_to_camera)
    np.testing.assert_array_equal(a[1].world_to_camera, c[1].world_to_camera)


def test_fallback_to_known_poses(tmp_path, monkeypatch):
    monkeypatch.setattr(demo, "_sfm", lambda *a, **k: None)
    with pytest.warns(UserWarning, match="SfM registered 0 of 6 views; using the known poses"):
        path = make_demo_scene(tmp_path / "known", seed=0, n_views=6, width=128, height=96)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = load_scene(path, images="images")
    gt = np.load(path / "ground_truth.npz", allow_pickle=False)
    assert len(scene) == 6 and len(scene.points) >= 30
    for cam, w2c in zip(scene.cameras, gt["world_to_camera"]):
        np.testing.assert_allclose(cam.world_to_camera, w2c, atol=1e-12)
        np.testing.assert_allclose(cam.K, gt["K"], rtol=1e-12)


def test_bad_arguments(tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(ConfigError, match="full: demo output folder exists and is not empty"):
        make_demo_scene(tmp_path / "full")
    with pytest.raises(ConfigError, match="n_views"):
        make_demo_scene(tmp_path / "a", n_views=2)
    with pytest.raises(ConfigError, match="width/height"):
        make_demo_scene(tmp_path / "b", width=8)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full"]
