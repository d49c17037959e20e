"""A small scene the project makes itself: a textured room corner, rendered and then SfM'd (DAT-15).

Three planes (floor + two walls) carry textures that ship inside scikit-image's wheel
(``skimage.data``: astronaut, chelsea, coffee).  A numpy ray-plane renderer draws them from V
cameras on an arc, the PNGs go to ``images/``, and pycolmap's CPU SfM (SIFT, exhaustive
matching, incremental mapping) writes ``sparse/0``.  Should SfM fail to register every view, the
known poses are written instead and points are triangulated with them (triangulate.py).

The result is an ordinary COLMAP scene: ``load_scene(path, images="images")``.  The true
cameras are kept in ``ground_truth.npz`` (w2c (V, 4, 4), K (3, 3); no pickles).
"""
from __future__ import annotations

import os
import shutil
import warnings
from pathlib import Path

import numpy as np

from ..errors import ConfigError, SceneError
from ..io.atomic import atomic_dir
from ..types import Camera

#: Bumped whenever the generated scene changes (names the cache folder).
DEMO_VERSION = 1

#: Room corner (world frame, y up, metres-ish): floor y=0 and walls x=-ROOM, z=-ROOM, each
#: extending ROOM (floor) / WALL_HEIGHT (walls).  Our choice.
ROOM = 2.0
WALL_HEIGHT = 2.4

#: Camera arc: distance from the look-at target, azimuth range (degrees, measured from +x
#: towards +z around the corner) and height.  The seed jitters each camera uniformly by up to
#: RADIUS_JITTER, HEIGHT_JITTER and AZIMUTH_JITTER_DEG (the height jitter keeps the camera path
#: off a single plane, which steadies SfM's focal length).  Our choice.
ARC_RADIUS = 3.2
ARC_AZIMUTH_DEG = (0.0, 90.0)
ARC_HEIGHT = 1.6
RADIUS_JITTER = 0.1
HEIGHT_JITTER = 0.4
AZIMUTH_JITTER_DEG = 2.0
LOOK_AT = (-0.9, 0.7, -0.9)

#: Horizontal field of view of the demo cameras (degrees).  Our choice.
FOV_X_DEG = 60.0

#: The default scene of demo_scene_path (the notebooks' and the tests'): views and image size.
#: `refgs demo` asks for a larger one (refgs.analysis.demo.DEMO_SCENE_SIZE).  Our choice.
DEMO_N_VIEWS = 12
DEMO_WIDTH = 160
DEMO_HEIGHT = 120

#: Supersampling per pixel axis (SS x SS rays, box-filtered) against texture aliasing.
SUPERSAMPLE = 3

#: Colour seen by rays that hit no plane.
SKY = (0.55, 0.65, 0.8)


def _textures():
    """(texture (h, w, 3) float in [0, 1]) for the floor, the back wall (z=-ROOM), the left wall
    (x=-ROOM): skimage.data images shipped in the wheel (deps.md note 1)."""
    from skimage import data

    return [np.asarray(img(), np.float64) / 255.0
            for img in (data.coffee, data.astronaut, data.chelsea)]


def _planes():
    """(origin, axis_u, axis_v, extent_u, extent_v) of the floor, back wall, left wall."""
    r, h = ROOM, WALL_HEIGHT
    return [
        (np.array([-r, 0.0, -r]), np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), 2 * r, 2 * r),
        (np.array([-r, h, -r]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0]), 2 * r, h),
        (np.array([-r, h, r]), np.array([0, 0, -1.0]), np.array([0, -1.0, 0]), 2 * r, h),
    ]


def demo_cameras(n_views: int, width: int, height: int, rng: np.random.Generator) -> list:
    """V cameras on the arc, looking at LOOK_AT, image y pointing down the world y axis."""
    f = 0.5 * width / np.tan(np.radians(FOV_X_DEG) / 2)
    az = np.radians(np.linspace(*ARC_AZIMUTH_DEG, n_views)
                    + rng.uniform(-AZIMUTH_JITTER_DEG, AZIMUTH_JITTER_DEG, n_views))
    radius = ARC_RADIUS + rng.uniform(-RADIUS_JITTER, RADIUS_JITTER, n_views)
    heights = ARC_HEIGHT + rng.uniform(-HEIGHT_JITTER, HEIGHT_JITTER, n_views)
    target = np.array(LOOK_AT)
    cams = []
    for a, rad, y in zip(az, radius, heights):
        eye = target + np.array([rad * np.cos(a), 0.0, rad * np.sin(a)])
        eye[1] = y
        cams.append(Camera.look_at(eye, target, up=(0.0, -1.0, 0.0), fx=f, width=width,
                                   height=height))
    return cams


def render_planes(camera: Camera, textures, planes) -> np.ndarray:
    """Ray-trace the textured planes: (H, W, 3) in [0, 1], SUPERSAMPLE^2 rays per pixel, nearest
    hit wins, bilinear texture lookup (texture row 0 at the plane's origin edge)."""
    from scipy.ndimage import map_coordinates

    H, W, s = camera.height, camera.width, SUPERSAMPLE
    sub = (np.arange(s) + 0.5) / s
    jj = (np.arange(W)[:, None] + sub[None, :]).ravel()
    ii = (np.arange(H)[:, None] + sub[None, :]).ravel()
    u, v = np.meshgrid(jj, ii)  # (H s, W s) continuous image coordinates (CNV-08)
    d_cam = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy,
                      np.ones_like(u)], -1)
    d = d_cam @ camera.rotation  # rows: R^T d_cam, world directions
    o = camera.center
    best_t = np.full(u.shape, np.inf)
    out = np.broadcast_to(np.asarray(SKY, float), u.shape + (3,)).copy()
    for tex, (p0, au, av, eu, ev) in zip(textures, planes):
        n = np.cross(au, av)
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((p0 - o) @ n) / denom
        hit = o + t[..., None] * d
        cu, cv = (hit - p0) @ au, (hit - p0) @ av
        ok = (np.abs(denom) > 1e-12) & (t > 0) & (t < best_t) & (cu >= 0) & (cu <= eu) \
            & (cv >= 0) & (cv <= ev)
        th, tw = tex.shape[:2]
        rows, cols = cv[ok] / ev * (th - 1), cu[ok] / eu * (tw - 1)
        out[ok] = np.stack([map_coordinates(tex[..., c], [rows, cols], order=1, mode="nearest")
                            for c in range(3)], -1)
        best_t[ok] = t[ok]
    return out.reshape(H, s, W, s, 3).mean(axis=(1, 3))


def _sfm(image_dir: Path, out_dir: Path, names: list, seed: int):
    """pycolmap SfM (SIFT, exhaustive matching, incremental mapping) on CPU, one thread;
    returns the largest reconstruction or None."""
    import pycolmap

    from .triangulate import NUM_THREADS, quiet_pycolmap

    db_path = out_dir.parent / "database.db"
    with quiet_pycolmap():
        pycolmap.set_random_seed(int(seed))
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = NUM_THREADS
        pycolmap.extract_features(db_path, image_dir, image_names=names,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = NUM_THREADS
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = int(seed)
        pycolmap.match_exhaustive(db_path, matching_options=matching,
                                  verification_options=verification, device=pycolmap.Device.cpu)
        pipeline = pycolmap.IncrementalPipelineOptions()
        pipeline.num_threads = NUM_THREADS
        pipeline.random_seed = int(seed)
        pipeline.multiple_models = False
        models = pycolmap.incremental_mapping(db_path, image_dir, out_dir, options=pipeline)
    if not models:
        return None
    return max(models.values(), key=lambda r: r.num_reg_images())


def make_demo_scene(out_dir, seed: int = 0, n_views: int = 12, width: int = 160,
                    height: int = 120) -> Path:
    """Render the room corner from ``n_views`` cameras and build its COLMAP model (DAT-15).

    Writes ``out_dir/images/view_XXX.png``, ``out_dir/sparse/0/*.bin``, ``ground_truth.npz``,
    atomically (built in a temporary sibling folder, then renamed).  ``out_dir`` must not exist
    or be empty.  Same seed -> same files.
    """
    from PIL import Image

    out_dir = Path(out_dir)
    if not (isinstance(n_views, (int, np.integer)) and n_views >= 3):
        raise ConfigError(f"demo n_views: expected an integer >= 3, got {n_views!r}")
    if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))
            and width >= 32 and height >= 32):
        raise ConfigError(f"demo width/height: expected integers >= 32, got {width}x{height}")
    if out_dir.exists() and any(out_dir.iterdir()):
        raise ConfigError(f"{out_dir}: demo output folder exists and is not empty")
    with atomic_dir(out_dir) as tmp:
        rng = np.random.default_rng(seed)
        cams = demo_cameras(int(n_views), int(width), int(height), rng)
        textures, planes = _textures(), _planes()
        image_dir = tmp / "images"
        image_dir.mkdir()
        names = [f"view_{k:03d}.png" for k in range(len(cams))]
        pixels = []
        for name, cam in zip(names, cams):
            rgb = render_planes(cam, textures, planes)
            q = np.clip(np.rint(rgb * 255), 0, 255).astype(np.uint8)
            Image.fromarray(q).save(image_dir / name)
            pixels.append(q / 255.0)
        np.savez(tmp / "ground_truth.npz", names=np.array(names),
                 world_to_camera=np.stack([c.world_to_camera for c in cams]), K=cams[0].K)
        model_dir = tmp / "sparse" / "0"
        model_dir.mkdir(parents=True)
        work = tmp / "sfm"
        (work / "out").mkdir(parents=True)
        rec = _sfm(image_dir, work / "out", names, seed)
        if rec is None or rec.num_reg_images() < len(names):
            got = 0 if rec is None else rec.num_reg_images()
            warnings.warn(f"demo scene: SfM registered {got} of {len(names)} views; using the "
                          "known poses and triangulating instead", stacklevel=2)
            from .triangulate import triangulate_known_poses

            rec = triangulate_known_poses([Path(n).stem for n in names], pixels, cams, work,
                                          "default", seed)
        if rec.num_points3D() == 0:
            raise SceneError(f"{out_dir}: demo scene: no 3D points were reconstructed")
        rec.write_binary(str(model_dir))
        shutil.rmtree(work)
    return out_dir


def demo_cache_root() -> Path:
    """$REFGS_CACHE, else $XDG_CACHE_HOME/refgs, else ~/.cache/refgs."""
    if os.environ.get("REFGS_CACHE"):
        return Path(os.environ["REFGS_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "refgs"


def demo_scene_path(width: int = DEMO_WIDTH, height: int = DEMO_HEIGHT) -> Path:
    """The demo scene (seed 0, DEMO_N_VIEWS views of ``width`` x ``height``), generated on first
    use into the user cache (``demo_cache_root()/demo-v{DEMO_VERSION}-{width}x{height}``);
    concurrent first uses are safe: each builds in its own temporary folder and the first rename
    wins."""
    final = demo_cache_root() / f"demo-v{DEMO_VERSION}-{width}x{height}"
    complete = final / "sparse" / "0" / "points3D.bin"
    if complete.is_file():
        return final
    try:
        make_demo_scene(final, n_views=DEMO_N_VIEWS, width=width, height=height)
    except (OSError, ConfigError):
        if not complete.is_file():  # not a concurrent first use that published before us
            raise
    return final


__all__ = ["make_demo_scene", "demo_scene_path", "demo_cache_root", "render_planes",
           "demo_cameras", "DEMO_VERSION", "DEMO_N_VIEWS", "DEMO_WIDTH", "DEMO_HEIGHT"]
