"""Points from the training views only, triangulated with the known poses (clause DAT-11).

The model's points3D come from ALL views (test views included), so a sparse-view run must not
use them.  As DropGaussian/FSGS (tools/colmap_llff.py, peers.md 3.1) we extract SIFT features from
the training images themselves, match them exhaustively, and triangulate with the poses and
intrinsics fixed (COLMAP ``point_triangulator``, here ``pycolmap.triangulate_points``).  They go
on to dense MVS (patch_match_stereo, CUDA only); we stop at the sparse points.

Everything runs on the CPU with one thread and a fixed seed, so the result is a function of the
images, cameras, options and seed.
"""
from __future__ import annotations

import shutil
import tempfile
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..errors import ConfigError, SceneError

#: Option presets: {"extraction": SiftExtractionOptions fields, "matching":
#: FeatureMatchingOptions fields, "triangulation": IncrementalTriangulatorOptions fields}.
#: "default" = pycolmap 4.2.1 defaults.  "tuned" = the DropGaussian feature options scaled to
#: images_8 (affine shape + domain-size pooling, up to 32768 features, guided matching;
#: tools/colmap_llff.py) plus a finer first octave (-2: the image upsampled 4x, COLMAP default
#: -1) and two-view tracks kept (COLMAP drops them by default), because 3 small views leave few
#: tracks longer than two.  Counts on fern (docs/spec/data.md, DAT-11): default ~100 points for
#: 3 views, tuned ~1000.
TRIANGULATION_PRESETS = {
    "default": {"extraction": {}, "matching": {}, "triangulation": {}},
    "tuned": {
        "extraction": {"first_octave": -2, "max_num_features": 32768,
                       "estimate_affine_shape": True, "domain_size_pooling": True},
        "matching": {"guided_matching": True},
        "triangulation": {"ignore_two_view_tracks": False},
    },
}

#: pycolmap runs single-threaded: thread scheduling would otherwise decide image ids and which
#: thread-local random stream a RANSAC draws from.  [DAT-11]
NUM_THREADS = 1

#: glog level while pycolmap runs (2 = errors only); restored afterwards.
QUIET_LOG_LEVEL = 2


@contextmanager
def quiet_pycolmap():
    import pycolmap

    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = QUIET_LOG_LEVEL
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def _apply(target, values: dict, where: str):
    for key, value in values.items():
        if not hasattr(target, key):
            raise ConfigError(f"triangulation options: {where} has no option {key!r}")
        setattr(target, key, value)


def _resolve(options) -> dict:
    if isinstance(options, str):
        if options not in TRIANGULATION_PRESETS:
            raise ConfigError(f"--triangulation: expected one of {sorted(TRIANGULATION_PRESETS)}, "
                              f"got {options!r}")
        return TRIANGULATION_PRESETS[options]
    extra = set(options) - {"extraction", "matching", "triangulation"}
    if extra:
        raise ConfigError(f"triangulation options: unknown groups {sorted(extra)}")
    return options


def triangulate_known_poses(names, images, cameras, work_dir, options="tuned", seed: int = 0):
    """Extract, match and triangulate ``images`` with the ``cameras`` held fixed (DAT-11).

    names    V file stems (unique), images V arrays (H, W, 3) in [0, 1], cameras V refgs.Camera
    Returns the pycolmap.Reconstruction (V cameras/images with the given poses, and the points
    with their tracks).  Intermediate files live in a temporary subfolder of ``work_dir``.
    """
    import pycolmap
    from PIL import Image

    opts = _resolve(options)
    if len(names) < 2:
        raise ConfigError(f"--views: triangulation needs at least 2 views, got {len(names)}")
    if len(set(names)) != len(names):
        raise ConfigError("triangulation: view names must be unique")
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="triangulate-", dir=work_dir))
    try:
        image_dir = tmp / "images"
        image_dir.mkdir()
        view_of = {}
        for k, (stem, pixels) in enumerate(zip(names, images)):
            # the working-resolution pixels, losslessly as PNG (what the trainer sees)
            q = np.clip(np.rint(np.asarray(pixels, np.float64) * 255), 0, 255).astype(np.uint8)
            Image.fromarray(q).save(image_dir / f"{stem}.png")
            view_of[f"{stem}.png"] = k
        files = sorted(view_of)
        db_path = tmp / "database.db"
        with quiet_pycolmap():
            pycolmap.set_random_seed(int(seed))
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = "PINHOLE"
            extraction = pycolmap.FeatureExtractionOptions()
            extraction.num_threads = NUM_THREADS
            _apply(extraction.sift, opts["extraction"], "extraction")
            pycolmap.extract_features(db_path, image_dir, image_names=files,
                                      camera_mode=pycolmap.CameraMode.PER_IMAGE,
                                      reader_options=reader, extraction_options=extraction,
                                      device=pycolmap.Device.cpu)
            rec = pycolmap.Reconstruction()
            with pycolmap.Database.open(db_path) as db:
                for im in sorted(db.read_all_images(), key=lambda m: m.image_id):
                    cam = cameras[view_of[im.name]]
                    colmap_cam = db.read_camera(im.camera_id)
                    colmap_cam.params = [cam.fx, cam.fy, cam.cx, cam.cy]
                    colmap_cam.has_prior_focal_length = True
                    db.update_camera(colmap_cam)
                    rec.add_camera_with_trivial_rig(colmap_cam)
                    pose = pycolmap.Rigid3d(np.asarray(cam.world_to_camera, np.float64)[:3, :4])
                    rec.add_image_with_trivial_frame(
                        pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id),
                        pose)
            if rec.num_images() != len(files):
                raise SceneError(f"{image_dir}: pycolmap read {rec.num_images()} of "
                                 f"{len(files)} images")
            matching = pycolmap.FeatureMatchingOptions()
            matching.num_threads = NUM_THREADS
            _apply(matching, opts["matching"], "matching")
            verification = pycolmap.TwoViewGeometryOptions()
            verification.ransac.random_seed = int(seed)
            pycolmap.match_exhaustive(db_path, matching_options=matching,
                                      verification_options=verification,
                                      device=pycolmap.Device.cpu)
            pipeline = pycolmap.IncrementalPipelineOptions()
            pipeline.num_threads = NUM_THREADS
            pipeline.random_seed = int(seed)
            pipeline.triangulation.random_seed = int(seed)
            _apply(pipeline.triangulation, opts["triangulation"], "triangulation")
            out_dir = tmp / "sparse"
            out_dir.mkdir()
            return pycolmap.triangulate_points(rec, db_path, image_dir, out_dir,
                                               clear_points=True, options=pipeline)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def triangulate_train_views(scene, train_idx, work_dir, options=TRIANGULATION_PRESETS["tuned"],
                            seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate points seen by the training views of ``scene`` (clause DAT-11).

    scene      a refgs.data.Scene (images and cameras are used; its points are not)
    train_idx  indices of the training views (>= 2)
    work_dir   folder for the intermediate database/images (a temporary subfolder, removed after)
    options    a preset name or dict of TRIANGULATION_PRESETS' form
    seed       COLMAP's random seed (pycolmap.set_random_seed and the pipeline's random_seed)

    Returns ``(points (P, 3) float64, colors (P, 3) float64 in [0, 1])`` sorted by COLMAP point id.
    """
    idx = [int(i) for i in train_idx]
    result = triangulate_known_poses([Path(scene.names[i]).stem for i in idx],
                                     [scene.images[i] for i in idx],
                                     [scene.cameras[i] for i in idx], work_dir, options, seed)
    ids = sorted(result.points3D)
    points = np.array([result.points3D[j].xyz for j in ids], np.float64).reshape(-1, 3)
    colors = np.array([result.points3D[j].color for j in ids], np.float64).reshape(-1, 3)
    if len(points) == 0:
        warnings.warn(f"triangulation of {len(idx)} training views gave no points", stacklevel=2)
    return points, colors / 255.0


__all__ = ["triangulate_train_views", "triangulate_known_poses", "TRIANGULATION_PRESETS"]
