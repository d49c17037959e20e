"""COLMAP scene loading (DAT-01..DAT-09): real scenes, rescaled intrinsics, and bad input.

Broken scenes are built in tmp_path from copies of fern's sparse/0 (../shared is never touched).
"""
from __future__ import annotations

import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import data_root

from refgs.data.colmap import MAX_DISTORTION_PX, corner_displacement, load_scene
from refgs.errors import ConfigError, SceneError

DATA = data_root()  # $REFGS_DATA or <repo>/../shared/data
FERN = DATA / "fern"
DESK = DATA / "desk"
needs_data = pytest.mark.skipif(not (FERN / "sparse" / "0").is_dir(),
                                reason="shared data not available")

FERN_F, FERN_K = 3260.5263328805895, 0.019750463822896944  # SOURCES.md / cameras.bin


def quiet_load(*args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_scene(*args, **kwargs)


def fern_copy(tmp_path, link_images=True) -> Path:
    """tmp scene: a copy of fern's sparse/0, and images_8 linked (or copied)."""
    scene = tmp_path / "fern"
    shutil.copytree(FERN / "sparse", scene / "sparse")
    for f in (scene / "sparse" / "0").iterdir():
        f.chmod(0o644)
    if link_images:
        (scene / "images_8").symlink_to(FERN / "images_8", target_is_directory=True)
    else:
        shutil.copytree(FERN / "images_8", scene / "images_8")
        for f in (scene / "images_8").iterdir():
            f.chmod(0o644)
    return scene


def fern_text_model(tmp_path, edit=None) -> Path:
    """tmp scene whose sparse/0 is fern's model written as text by pycolmap; ``edit`` rewrites
    the camera line of cameras.txt."""
    import pycolmap

    scene = tmp_path / "fern_txt"
    model = scene / "sparse" / "0"
    model.mkdir(parents=True)
    pycolmap.Reconstruction(str(FERN / "sparse" / "0")).write_text(str(model))
    if edit is not None:
        lines = (model / "cameras.txt").read_text().splitlines()
        lines = [edit(ln) if ln and not ln.startswith("#") else ln for ln in lines]
        (model / "cameras.txt").write_text("\n".join(lines) + "\n")
    (scene / "images_8").symlink_to(FERN / "images_8", target_is_directory=True)
    return scene


def to_binary(scene: Path) -> Path:
    """Convert the scene's text model to binary with pycolmap (text files removed)."""
    import pycolmap

    model = scene / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    for f in model.iterdir():
        f.unlink()
    rec.write_binary(str(model))
    return scene


# --------------------------------------------------------------------------------------------
# Real scenes
# --------------------------------------------------------------------------------------------

@needs_data
def test_fern_loads_with_rescaled_intrinsics_and_distortion_warning():
    expected = r"SIMPLE_RADIAL \(k1=0.0197505\).*corner displacement 3.72 px"
    with pytest.warns(UserWarning, match=expected):
        scene = load_scene(FERN)
    assert scene.names == [f"IMG_{4026 + k}.png" for k in range(20)]
    assert scene.model_names[0] == "IMG_4026.JPG"
    assert len(scene.cameras) == len(scene.images) == 20
    assert scene.points.shape == (10091, 3) and scene.point_colors.shape == (10091, 3)
    assert 0 <= scene.point_colors.min() and scene.point_colors.max() <= 1
    img = scene.images[0]
    assert img.shape == (378, 504, 3) and img.dtype == np.float64
    assert 0.0 <= img.min() and img.max() <= 1.0 and img.max() > 0.5
    cam = scene.cameras[0]
    assert (cam.width, cam.height) == (504, 378)
    np.testing.assert_allclose(cam.K, [[FERN_F * 504 / 4032, 0, 2016 * 504 / 4032],
                                       [0, FERN_F * 378 / 3024, 1512 * 378 / 3024], [0, 0, 1]],
                               rtol=1e-15)
    assert scene.camera_models == ["SIMPLE_RADIAL"] * 20


@needs_data
def test_poses_match_pycolmap_and_project_observations():
    """DAT-03: w2c = cam_from_world; projecting each observed 3D point with our pinhole lands on
    its recorded 2D point (scaled to images_8) within the radial displacement bound."""
    import pycolmap

    scene = quiet_load(FERN)
    rec = pycolmap.Reconstruction(str(FERN / "sparse" / "0"))
    bound = corner_displacement("SIMPLE_RADIAL", [FERN_F / 8, 252, 189, FERN_K], 504, 378)
    assert 3.7 < bound < 3.75
    for v in (0, 11):
        im = rec.images[scene.image_ids[v]]
        cam = scene.cameras[v]
        np.testing.assert_array_equal(cam.world_to_camera[:3], im.cam_from_world().matrix())
        np.testing.assert_allclose(cam.center, im.projection_center(), atol=1e-9)
        obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
        xy = np.array([o[0] for o in obs]) * (504 / 4032)
        X = np.array([o[1] for o in obs]) @ cam.rotation.T + cam.translation
        uv = X[:, :2] / X[:, 2:] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        err = np.linalg.norm(uv - xy, axis=1)
        assert len(err) > 500
        assert err.max() <= bound + 1e-6
        assert err.max() > 0.5 * bound  # the distortion is really there


@pytest.mark.skipif(not (DESK / "sparse" / "0").is_dir(), reason="shared data not available")
def test_desk_pinhole_reprojection_at_quarter_resolution():
    """desk: PINHOLE 1906x1070 loaded at 476x268 (fx, cx by 476/1906; fy, cy by 268/1070)."""
    import pycolmap

    scene = load_scene(DESK)
    cam = scene.cameras[0]
    np.testing.assert_allclose([cam.fx, cam.fy], [1510.85 * 476 / 1906, 1501.54 * 268 / 1070],
                               rtol=1e-5)
    rec = pycolmap.Reconstruction(str(DESK / "sparse" / "0"))
    im = rec.images[scene.image_ids[0]]
    obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
    xy = np.array([o[0] for o in obs]) * [476 / 1906, 268 / 1070]
    X = np.array([o[1] for o in obs]) @ cam.rotation.T + cam.translation
    uv = X[:, :2] / X[:, 2:] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    # SOURCES.md: mean reprojection error 1.06 px at full size, i.e. ~0.26 px here
    assert np.median(np.linalg.norm(uv - xy, axis=1)) < 0.5


@needs_data
def test_float32_dtype():
    scene = quiet_load(FERN, dtype=np.float32)
    assert scene.images[3].dtype == np.float32
    assert scene.points.dtype == np.float32 and scene.point_colors.dtype == np.float32


@needs_data
def test_resolution_factor_uses_python_round_and_bicubic():
    from PIL import Image

    scene = quiet_load(FERN, resolution=4)
    # 504/4 = 126, 378/4 = 94.5 -> round half to even -> 94
    assert scene.images[0].shape == (94, 126, 3)
    cam = scene.cameras[0]
    np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy],
                               [FERN_F * 126 / 4032, FERN_F * 94 / 3024, 2016 * 126 / 4032,
                                1512 * 94 / 3024], rtol=1e-15)
    with Image.open(FERN / "images_8" / "IMG_4026.png") as im:
        expect = np.asarray(im.convert("RGB").resize((126, 94), Image.Resampling.BICUBIC)) / 255.0
    np.testing.assert_array_equal(scene.images[0], expect)


@pytest.mark.parametrize("bad", [0.5, 0, -8, float("nan"), "8"])
def test_bad_resolution_names_the_flag(bad):
    if not FERN.is_dir():
        pytest.skip("shared data not available")
    with pytest.raises(ConfigError, match="--resolution"):
        load_scene(FERN, resolution=bad)


@needs_data
def test_text_model_loads_like_binary(tmp_path):
    a = quiet_load(FERN)
    b = quiet_load(fern_text_model(tmp_path))
    assert b.names == a.names
    np.testing.assert_allclose(b.points, a.points, rtol=1e-12)
    for ca, cb in zip(a.cameras, b.cameras):
        np.testing.assert_allclose(cb.K, ca.K, rtol=1e-12)
        np.testing.assert_allclose(cb.world_to_camera, ca.world_to_camera, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Cameras refused
# --------------------------------------------------------------------------------------------

@needs_data
def test_distortion_above_limit_refused(tmp_path):
    # k = 0.05: corner displacement 3.72 * 0.05 / 0.01975 = 9.4 px at 504x378 > 5
    scene = fern_text_model(tmp_path, lambda ln: ln.replace("0.019750463822896944", "0.05"))
    expected = r"cameras.txt.*SIMPLE_RADIAL.*9.4\d px.*MAX_DISTORTION_PX"
    with pytest.raises(SceneError, match=expected):
        load_scene(scene)
    assert MAX_DISTORTION_PX == 5


@needs_data
def test_same_distortion_accepted_at_lower_resolution(tmp_path):
    scene = fern_text_model(tmp_path, lambda ln: ln.replace("0.019750463822896944", "0.05"))
    with pytest.warns(UserWarning, match=r"k1=0.05\).*corner displacement 4.7\d px"):
        load_scene(scene, resolution=2)


@needs_data
@pytest.mark.parametrize("f", ["0", "-3260.5"])
def test_non_positive_focal_refused_naming_the_file(tmp_path, f):
    scene = to_binary(fern_text_model(tmp_path, lambda ln: ln.replace("3260.5263328805895", f)))
    with pytest.raises(SceneError, match=r"cameras\.bin.*non-positive focal length"):
        load_scene(scene)


@needs_data
@pytest.mark.parametrize("binary", [False, True])
def test_unsupported_camera_model_refused(tmp_path, binary):
    fisheye = "1 OPENCV_FISHEYE 4032 3024 3260.5 3260.5 2016 1512 0.01 0 0 0"
    scene = fern_text_model(tmp_path, lambda ln: fisheye)
    if binary:
        to_binary(scene)
    name = "cameras.bin" if binary else "cameras.txt"
    with pytest.raises(SceneError, match=rf"{name}.*OPENCV_FISHEYE.*supported: SIMPLE_PINHOLE"):
        load_scene(scene)


# --------------------------------------------------------------------------------------------
# Corrupt binary models (pycolmap alone would load zeros or hang)
# --------------------------------------------------------------------------------------------

@needs_data
@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
@pytest.mark.parametrize("cut", [0.5, 1, 8])
def test_truncated_binary_file_names_the_file(tmp_path, name, cut):
    """cut < 1: keep that fraction; cut >= 1: drop the last ``cut`` bytes."""
    scene = fern_copy(tmp_path)
    path = scene / "sparse" / "0" / name
    data = path.read_bytes()
    keep = int(len(data) * cut) if cut < 1 else len(data) - int(cut)
    path.write_bytes(data[:keep])
    with pytest.raises(SceneError, match=rf"{name}: (truncated|corrupt)"):
        load_scene(scene)


@needs_data
@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_trailing_bytes_and_bad_header(tmp_path, name):
    scene = fern_copy(tmp_path)
    path = scene / "sparse" / "0" / name
    data = path.read_bytes()
    path.write_bytes(data + b"\0" * 7)
    with pytest.raises(SceneError, match=rf"{name}: corrupt: 7 unexpected bytes"):
        load_scene(scene)
    path.write_bytes((10**12).to_bytes(8, "little") + data[8:])  # absurd record count
    with pytest.raises(SceneError, match=rf"{name}: (truncated|corrupt)"):
        load_scene(scene)


@needs_data
def test_empty_file_and_missing_file(tmp_path):
    scene = fern_copy(tmp_path)
    (scene / "sparse" / "0" / "images.bin").write_bytes(b"")
    with pytest.raises(SceneError, match=r"images\.bin: truncated"):
        load_scene(scene)
    (scene / "sparse" / "0" / "images.bin").unlink()
    with pytest.raises(SceneError, match=r"sparse/0: expected cameras\.bin, images\.bin"):
        load_scene(scene)


# --------------------------------------------------------------------------------------------
# Folders and matching
# --------------------------------------------------------------------------------------------

def test_missing_scene_folder(tmp_path):
    with pytest.raises(SceneError, match=r"nowhere: scene folder not found"):
        load_scene(tmp_path / "nowhere")


def test_missing_model_folder(tmp_path):
    (tmp_path / "images_8").mkdir()
    with pytest.raises(SceneError, match=r"sparse/0: COLMAP model folder not found"):
        load_scene(tmp_path)


@needs_data
def test_missing_and_empty_image_folder(tmp_path):
    scene = fern_copy(tmp_path)
    with pytest.raises(SceneError, match=r"images: image folder not found \(available: images_8\)"):
        load_scene(scene, images="images")
    (scene / "images").mkdir()
    (scene / "images" / "notes.txt").write_text("not an image")
    with pytest.raises(SceneError, match=r"images: no image files"):
        load_scene(scene, images="images")


@needs_data
def test_unmatched_files_skipped_with_warning_or_refused_in_strict_mode(tmp_path):
    scene = fern_copy(tmp_path, link_images=False)
    (scene / "images_8" / "IMG_4030.png").unlink()                     # model entry, no file
    shutil.copy(FERN / "images_8" / "IMG_4031.png", scene / "images_8" / "extra.png")  # no entry
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loaded = load_scene(scene)
    skipped = [str(w.message) for w in caught if "image(s) skipped" in str(w.message)]
    assert len(skipped) == 1, [str(w.message) for w in caught]
    assert re.search(r"2 image\(s\) skipped.*IMG_4030\.JPG has no file.*extra\.png has no entry",
                     skipped[0])
    assert len(loaded) == 19
    assert "IMG_4030.png" not in loaded.names and "extra.png" not in loaded.names
    with pytest.raises(SceneError, match=r"IMG_4030\.JPG has no file.*strict mode"):
        load_scene(scene, strict=True)
    (scene / "images_8" / "extra.png").unlink()
    with pytest.raises(SceneError, match=r"IMG_4030\.JPG has no file"):
        load_scene(scene, strict=True)


@needs_data
def test_duplicate_stems_and_unreadable_image(tmp_path):
    scene = fern_copy(tmp_path, link_images=False)
    bad = scene / "images_8" / "IMG_4028.png"
    bad.write_bytes(b"this is not a png")
    with pytest.raises(SceneError, match=r"IMG_4028\.png: cannot read image"):
        quiet_load(scene)
    (scene / "images_8" / "IMG_4028.jpg").write_bytes(b"")
    with pytest.raises(SceneError, match=r"two images share the stem 'IMG_4028'"):
        load_scene(scene)


@needs_data
def test_no_image_matches_the_model(tmp_path):
    scene = fern_copy(tmp_path)
    (scene / "other").mkdir()
    shutil.copy(FERN / "images_8" / "IMG_4026.png", scene / "other" / "unrelated.png")
    with pytest.raises(SceneError, match=r"no image in .*other matches an entry"):
        quiet_load(scene, images="other")


@needs_data
def test_select_keeps_views_in_given_order():
    scene = quiet_load(FERN)
    sub = scene.select([19, 1])
    assert sub.names == ["IMG_4045.png", "IMG_4027.png"]
    assert sub.cameras[0] is scene.cameras[19] and sub.images[1] is scene.images[1]
    assert sub.points is scene.points
