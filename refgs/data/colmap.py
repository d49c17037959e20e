"""Load a COLMAP scene (a ``sparse/0`` model + an image folder) into refgs cameras and images.

The model is read by pycolmap (``pycolmap.Reconstruction``); this module only checks it first,
matches model entries to image files, rescales intrinsics to the images' real size and turns
poses into :class:`refgs.Camera` objects.  Rules: clauses DAT-01..DAT-09 of docs/spec/data.md.

Layout::

    <scene_dir>/<images>/        image files (png, jpg, ...), matched to the model by file stem
    <scene_dir>/sparse/0/        cameras, images, points3D as .bin (preferred) or .txt
"""
from __future__ import annotations

import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError, SceneError
from ..types import Camera

#: Largest displacement (pixels, at the working resolution) of an image corner under a
#: SIMPLE_RADIAL / RADIAL distortion for which the camera is still treated as a pinhole.
#: Our choice: it admits LLFF fern (k = 0.0198, 3.7 px at 504x378; NeRF/3DGS LLFF loaders treat
#: it as a pinhole) and refuses the same camera at full resolution (30 px).  [DAT-04]
MAX_DISTORTION_PX = 5.0

#: Resampling filter for ``resolution=f`` (Pillow ``Image.resize`` default for RGB images, which
#: is what DropGaussian utils/camera_utils.py:25 ``pil_image.resize(resolution)`` uses).  [DAT-05]
RESIZE_FILTER = "BICUBIC"

#: Largest relative difference between the horizontal and vertical rescale factors
#: (W_img / camera.width vs H_img / camera.height) accepted as "the same image, resized".
#: Our choice; the shared scenes differ by at most 0.3 % (desk 476/1906 vs 268/1070).  [DAT-03]
MAX_ASPECT_MISMATCH = 0.02

#: File suffixes read as images (case-insensitive); other files in the folder are ignored.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")

#: Camera models used as they are, and the radial ones used as a pinhole when the distortion is
#: small (COLMAP src/colmap/sensor/models.h parameter orders).  [DAT-04]
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
RADIAL_MODELS = ("SIMPLE_RADIAL", "RADIAL")

#: The three files of COLMAP's classic model, binary and text.
MODEL_FILES = ("cameras", "images", "points3D")


@dataclass
class Scene:
    """A loaded scene: V views sorted by image file name, and the model's P points.

    names         list[str] (V,) image file names on disk, in Python ``sorted()`` order
    cameras       list[Camera] (V,) intrinsics rescaled to the loaded image size (DAT-03)
    images        list[ndarray] (V,) each (H, W, 3) in [0, 1], dtype as requested
    points        (P, 3) SfM points of the model (reconstructed from ALL views: see DAT-11)
    point_colors  (P, 3) their colours in [0, 1]
    model_dir     the sparse/0 folder read;  image_dir  the image folder read
    model_names   list[str] (V,) the matching names stored in the model (e.g. ``IMG_4026.JPG``)
    image_ids     list[int] (V,) COLMAP image ids
    camera_models list[str] (V,) COLMAP camera model names before conversion to a pinhole
    """

    names: list
    cameras: list
    images: list
    points: np.ndarray
    point_colors: np.ndarray
    model_dir: Path
    image_dir: Path
    model_names: list = field(default_factory=list)
    image_ids: list = field(default_factory=list)
    camera_models: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.names)

    def select(self, indices) -> "Scene":
        """The views ``indices`` (in that order); points are kept as they are."""
        idx = [int(i) for i in indices]
        pick = lambda xs: [xs[i] for i in idx] if xs else []  # noqa: E731
        return Scene(pick(self.names), pick(self.cameras), pick(self.images), self.points,
                     self.point_colors, self.model_dir, self.image_dir, pick(self.model_names),
                     pick(self.image_ids), pick(self.camera_models))


# --------------------------------------------------------------------------------------------
# Binary model check (before pycolmap sees the files)
# --------------------------------------------------------------------------------------------

def _num_params(model_id: int, path: Path, record: int) -> int:
    import pycolmap

    try:
        model = pycolmap.CameraModelId(model_id)
        return len(pycolmap.Camera.create_from_model_id(1, model, 1.0, 1, 1).params)
    except Exception:
        raise SceneError(f"{path}: camera record {record} has unknown camera model id {model_id}"
                         " (file corrupt?)") from None


def _need(data: bytes, pos: int, size: int, path: Path, what: str) -> None:
    if pos + size > len(data):
        raise SceneError(f"{path}: truncated or corrupt: {what} needs {size} bytes at offset "
                         f"{pos}, but the file has {len(data)} bytes")


def _check_records(path: Path, fixed: int, variable) -> None:
    """Walk ``uint64 count`` + ``count`` records; ``variable(data, pos, i) -> end of record``."""
    data = path.read_bytes()
    _need(data, 0, 8, path, "the header (record count)")
    (count,) = struct.unpack_from("<Q", data, 0)
    pos = 8
    for i in range(1, count + 1):
        _need(data, pos, fixed, path, f"record {i} of {count}")
        pos = variable(data, pos, i)
    if pos != len(data):
        raise SceneError(f"{path}: corrupt: {len(data) - pos} unexpected bytes after the {count} "
                         "records declared in its header")


def check_binary_model(model_dir: str | Path) -> None:
    """Check that cameras.bin, images.bin and points3D.bin hold exactly the records their headers
    declare (COLMAP's legacy binary layout, src/colmap/scene/reconstruction_io_binary.cc).

    pycolmap 4.2.1 reads a truncated cameras.bin silently (zero parameters) and never returns
    on a truncated points3D.bin, so this runs first.  Raises SceneError naming the file. [DAT-07]
    """
    model_dir = Path(model_dir)

    cams = model_dir / "cameras.bin"

    def camera(data, pos, i):  # int32 id, int32 model, uint64 width, uint64 height, params
        _, model_id, _, _ = struct.unpack_from("<iiQQ", data, pos)
        n = 8 * _num_params(model_id, cams, i)
        _need(data, pos + 24, n, cams, f"the parameters of camera record {i}")
        return pos + 24 + n

    _check_records(cams, 24, camera)

    imgs = model_dir / "images.bin"

    def image(data, pos, i):  # int32 id, 4+3 doubles, int32 camera, name\0, uint64 n, n*24
        end = data.find(b"\0", pos + 64)
        if end < 0:
            raise SceneError(f"{imgs}: truncated or corrupt: the name of image record {i} "
                             "has no terminating NUL")
        _need(data, end + 1, 8, imgs, f"the 2D point count of image record {i}")
        (n,) = struct.unpack_from("<Q", data, end + 1)
        _need(data, end + 9, 24 * n, imgs, f"the {n} 2D points of image record {i}")
        return end + 9 + 24 * n

    _check_records(imgs, 64, image)

    pts = model_dir / "points3D.bin"

    def point(data, pos, i):  # uint64 id, 3 doubles, 3 uint8, double error, uint64 n, n*8
        (n,) = struct.unpack_from("<Q", data, pos + 43)
        _need(data, pos + 51, 8 * n, pts, f"the track (length {n}) of point record {i}")
        return pos + 51 + 8 * n

    _check_records(pts, 51, point)


# --------------------------------------------------------------------------------------------
# Model, images, cameras
# --------------------------------------------------------------------------------------------

def model_format(model_dir: Path) -> str:
    """".bin" when all three binary files exist, else ".txt" when all three text files do
    (COLMAP's own preference); SceneError otherwise.  [DAT-01]"""
    if not model_dir.is_dir():
        raise SceneError(f"{model_dir}: COLMAP model folder not found (expected sparse/0 with "
                         "cameras, images, points3D as .bin or .txt)")
    kind = next((ext for ext in (".bin", ".txt")
                 if all((model_dir / (f + ext)).is_file() for f in MODEL_FILES)), None)
    if kind is None:
        raise SceneError(f"{model_dir}: expected cameras.bin, images.bin, points3D.bin (or the "
                         f".txt files); found {sorted(p.name for p in model_dir.iterdir())}")
    return kind


def read_model(model_dir: str | Path):
    """Check and read a classic COLMAP model folder with pycolmap (binary preferred). [DAT-01]"""
    import pycolmap

    model_dir = Path(model_dir)
    kind = model_format(model_dir)
    if kind == ".bin":
        check_binary_model(model_dir)
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises plain RuntimeError / ValueError on bad files
        last = str(exc).strip().splitlines()[-1] if str(exc).strip() else repr(exc)
        raise SceneError(f"{model_dir}: pycolmap could not read the {kind} model: {last}") from None


def list_images(image_dir: Path) -> dict[str, Path]:
    """Image files of ``image_dir`` by stem; SceneError when absent, empty or stems collide."""
    if not image_dir.is_dir():
        others = sorted(p.name for p in image_dir.parent.glob("images*") if p.is_dir())
        raise SceneError(f"{image_dir}: image folder not found"
                         + (f" (available: {', '.join(others)})" if others else ""))
    files = sorted(p for p in image_dir.iterdir()
                   if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise SceneError(f"{image_dir}: no image files (expected {', '.join(IMAGE_SUFFIXES)})")
    by_stem: dict[str, Path] = {}
    for p in files:
        if p.stem in by_stem:
            raise SceneError(f"{image_dir}: two images share the stem {p.stem!r} "
                             f"({by_stem[p.stem].name}, {p.name}); cannot match them to the model")
        by_stem[p.stem] = p
    return by_stem


def load_image(path: Path, factor: float | None = None, dtype=np.float64) -> np.ndarray:
    """Read an image as (H, W, 3) in [0, 1]; with ``factor`` resize to (round(W/f), round(H/f))
    with Pillow's RESIZE_FILTER (Python round, as DropGaussian).  [DAT-05]"""
    from PIL import Image

    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info):
                warnings.warn(f"{path}: alpha channel ignored", stacklevel=3)
            rgb = im.convert("RGB")
    except Exception as exc:
        raise SceneError(f"{path}: cannot read image ({exc})") from None
    if factor is not None and factor != 1:
        w, h = rgb.size
        size = (max(1, round(w / factor)), max(1, round(h / factor)))
        rgb = rgb.resize(size, resample=getattr(Image.Resampling, RESIZE_FILTER))
    return (np.asarray(rgb, dtype=np.float64) / 255.0).astype(dtype)


def corner_displacement(model: str, params, width: int, height: int) -> float:
    """Largest displacement in pixels of an image corner under COLMAP's radial distortion
    ``u_d = u (1 + k1 r^2 + k2 r^4)`` (params at this width/height).  [DAT-04]"""
    p = np.asarray(params, float)
    f, cx, cy = p[0], p[1], p[2]
    k1 = p[3]
    k2 = p[4] if model == "RADIAL" else 0.0
    corners = np.array([[0, 0], [width, 0], [0, height], [width, height]], float)
    u = (corners - [cx, cy]) / f
    r2 = (u ** 2).sum(1)
    return float((f * np.sqrt(r2) * np.abs(k1 * r2 + k2 * r2 ** 2)).max())


def to_camera(cam, cam_from_world, width: int, height: int, cam_file: Path,
              image_name: str, warn: bool = True) -> Camera:
    """A pycolmap camera + pose -> refgs Camera at (width, height); ``warn`` emits the
    radial-as-pinhole warning (load_scene: once per camera).  [DAT-03, DAT-04]"""
    model = cam.model.name
    p = np.asarray(cam.params, float)
    if model not in PINHOLE_MODELS + RADIAL_MODELS:
        raise SceneError(f"{cam_file}: camera {cam.camera_id} (image {image_name}) has model "
                         f"{model}; supported: {', '.join(PINHOLE_MODELS + RADIAL_MODELS)}")
    if not np.all(np.isfinite(p)):
        raise SceneError(f"{cam_file}: camera {cam.camera_id} has non-finite parameters {p}")
    if not (cam.width > 0 and cam.height > 0):
        raise SceneError(f"{cam_file}: camera {cam.camera_id} has size {cam.width}x{cam.height}; "
                         "expected positive")
    sx, sy = width / cam.width, height / cam.height
    if abs(sx / sy - 1.0) > MAX_ASPECT_MISMATCH:
        raise SceneError(f"{cam_file}: camera {cam.camera_id} is {cam.width}x{cam.height} but "
                         f"image {image_name} is {width}x{height}: aspect ratios differ")
    if model == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    else:
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    if not (fx > 0 and fy > 0):
        raise SceneError(f"{cam_file}: camera {cam.camera_id} has non-positive focal length "
                         f"(fx={fx}, fy={fy}); expected > 0")
    K = np.array([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]])
    if model in RADIAL_MODELS:
        scaled = np.concatenate([[p[0] * sx, p[1] * sx, p[2] * sy], p[3:]])
        shift = corner_displacement(model, scaled, width, height)
        ks = ", ".join(f"k{i + 1}={k:.6g}" for i, k in enumerate(p[3:]))
        if shift > MAX_DISTORTION_PX:
            raise SceneError(
                f"{cam_file}: camera {cam.camera_id} is {model} ({ks}); its distortion moves the "
                f"image corners by {shift:.2f} px at {width}x{height}, above MAX_DISTORTION_PX="
                f"{MAX_DISTORTION_PX:g}; undistort the images (colmap image_undistorter) first")
        if warn:
            warnings.warn(f"{cam_file}: camera {cam.camera_id} is {model} ({ks}); treated as a "
                          f"pinhole: corner displacement {shift:.2f} px at {width}x{height} "
                          f"(<= MAX_DISTORTION_PX={MAX_DISTORTION_PX:g})", stacklevel=3)
    w2c = np.eye(4)
    w2c[:3, :4] = np.asarray(cam_from_world.matrix(), float)
    return Camera(w2c, K, int(width), int(height))


# --------------------------------------------------------------------------------------------
# load_scene
# --------------------------------------------------------------------------------------------

def load_scene(scene_dir: str | Path, images: str = "images_8", resolution: float | None = None,
               strict: bool = False, dtype=np.float64) -> Scene:
    """Load ``scene_dir/images`` and ``scene_dir/sparse/0`` (clauses DAT-01..DAT-09).

    resolution  None: use the files as they are; f >= 1: resize each to (round(W/f), round(H/f))
                (``--images images --resolution 8`` = DropGaussian's ``-r 8``).
    strict      True: a model entry without an image file, an image without a model entry, or a
                model image without a pose raises SceneError; False: skipped with a warning.
    dtype       float dtype of images, points and colours (cameras are always float64).
    """
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        raise SceneError(f"{scene_dir}: scene folder not found")
    if resolution is not None and not (isinstance(resolution, (int, float, np.number))
                                       and np.isfinite(resolution) and resolution >= 1):
        raise ConfigError(f"--resolution: expected a downsampling factor >= 1, got {resolution!r}")
    model_dir = scene_dir / "sparse" / "0"
    image_dir = scene_dir / images
    rec = read_model(model_dir)
    files = list_images(image_dir)
    ext = model_format(model_dir)
    cam_file = model_dir / ("cameras" + ext)

    entries: dict[str, object] = {}
    problems: list[str] = []
    for im in rec.images.values():
        stem = Path(im.name).stem
        if stem in entries:
            raise SceneError(f"{model_dir / ('images' + ext)}: two entries share the stem {stem!r}")
        if not im.has_pose:
            problems.append(f"model image {im.name} has no pose (not registered)")
            continue
        entries[stem] = im
    problems += [f"model image {entries[s].name} has no file in {image_dir}"
                 for s in sorted(entries) if s not in files]
    problems += [f"image {files[s].name} has no entry in {model_dir}"
                 for s in sorted(files) if s not in entries]
    if problems:
        msg = f"{scene_dir}: {len(problems)} image(s) skipped: " + "; ".join(problems[:5]) + (
            " ..." if len(problems) > 5 else "")
        if strict:
            raise SceneError(msg + " (strict mode)")
        warnings.warn(msg, stacklevel=2)
    matched = sorted((files[s] for s in entries if s in files), key=lambda p: p.name)
    if not matched:
        raise SceneError(f"{scene_dir}: no image in {image_dir} matches an entry of {model_dir}")

    names, cameras, pixels, model_names, image_ids, models = [], [], [], [], [], []
    warned: set = set()
    for path in matched:
        im = entries[path.stem]
        rgb = load_image(path, resolution, dtype)
        cam = rec.cameras[im.camera_id]
        warn = (cam.camera_id, rgb.shape) not in warned
        warned.add((cam.camera_id, rgb.shape))
        cameras.append(to_camera(cam, im.cam_from_world(), rgb.shape[1], rgb.shape[0],
                                 cam_file, path.name, warn=warn))
        names.append(path.name)
        pixels.append(rgb)
        model_names.append(im.name)
        image_ids.append(int(im.image_id))
        models.append(cam.model.name)

    ids = sorted(rec.points3D)
    points = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    colors = np.array([rec.points3D[i].color for i in ids], dtype=np.float64).reshape(-1, 3)
    return Scene(names, cameras, pixels, points.astype(dtype), (colors / 255.0).astype(dtype),
                 model_dir, image_dir, model_names, image_ids, models)


__all__ = ["Scene", "load_scene", "read_model", "check_binary_model", "load_image",
           "corner_displacement", "to_camera", "MAX_DISTORTION_PX", "RESIZE_FILTER",
           "MAX_ASPECT_MISMATCH"]
