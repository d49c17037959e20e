"""refgs.fast.render / render_backward: the reference's API on the numba kernels.

Stages (the same as refgs.render, clause ids there):

    validate_inputs (numpy, O(N))  ->  gaussians_forward (covariance, projection, SH; per Gaussian)
    -> stable depth sort (numpy, parts on the threads, merged: depth_order)
    -> live_intersections (the screen per Gaussian and tile of its rectangle, on the threads)
       + build_tile_lists (counting sort of the live ones, chunks of Gaussians on the threads)
    -> composite_forward (per tile)

and backward

    composite_backward (per tile, a per-intersection buffer) -> reduce_by_gaussian (per
    Gaussian, intersection order; bands of Gaussians in parallel)
    -> gaussians_backward (per Gaussian).

Every kernel is compiled once per dtype (float32 / float64) and cached on disk (numba
``cache=True``); computation happens in the Gaussians' dtype (CNV-11), except for the per-Gaussian
stage of a float32 render with ``geometry="float64"`` (GEOMETRY_PRECISIONS).

Parallelism.  The kernels are plain ``nogil`` numba functions over a range of work items (tiles or
Gaussians); :func:`parallel_for` cuts the range into chunks and runs them on a thread pool of
``numba.get_num_threads()`` threads (set it with ``numba.set_num_threads`` or NUMBA_NUM_THREADS).
Every work item writes only its own outputs, so results are bit-identical for any thread count
and schedule.  (Numba's ``parallel=True`` would do the same but multiplies compile time.)
"""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

from ..constants import ALPHA_MIN, T_MIN
from ..projection import frustum_limits
from ..rasterize import tile_grid
from ..render import resolve_profile, validate_inputs
from ..types import Gradients, RenderConfig, RenderOutput
from . import gaussians as gk
from . import kernels as rk
from . import tiles as tl

#: marker stored in RenderOutput.cache by :func:`render` (what :func:`render_backward` accepts)
CACHE_TAG = "refgs.fast"
#: work items per thread and call: more chunks balance uneven tiles, fewer cost less overhead
CHUNKS_PER_THREAD = 8
#: Gaussians per chunk at least (the per-Gaussian kernels are cheap per item)
MIN_GAUSSIAN_CHUNK = 2048
#: Gaussians per chunk of the tile-list passes at least; they run one chunk per thread (each
#: chunk keeps its own per-tile count rows, and more chunks made the scattered writes of the
#: second pass slower: 4.0 ms against 5.2 ms with 8 chunks per thread, 130k Gaussians, 2 threads)
MIN_LIST_CHUNK = 2048
#: precision choices of the per-Gaussian stage (covariance, projection, SH, culls, radii, tile
#: rectangles, depths and so the depth order) for float32 Gaussians: "input" (default, CNV-11:
#: everything in the Gaussians' dtype, a model of a float32 GPU backend) or "float64" (an
#: explicit mixed precision: that stage in float64, its outputs rounded to float32 for the
#: compositing -- except the 2D means, which the compositing carries as float32 value + float32
#: residual -- so every per-Gaussian decision is the float64 one and pixel offsets keep float64's
#: position: no geometric or depth-order near-ties; docs/fast.md "Mixed precision").
#: Float64 Gaussians: float64 either way.
GEOMETRY_PRECISIONS = ("input", "float64")

_pool_lock = threading.Lock()
_pool: dict = {}


def _executor(n_threads: int) -> ThreadPoolExecutor:
    with _pool_lock:
        ex = _pool.get(n_threads)
        if ex is None:
            ex = _pool[n_threads] = ThreadPoolExecutor(n_threads, thread_name_prefix="refgs-fast")
        return ex


def chunk_length(n_items: int, min_chunk: int = 1) -> int:
    """Items per chunk of :func:`parallel_for` (CHUNKS_PER_THREAD chunks per thread, at least
    ``min_chunk`` items each): its calls are kernel(lo, lo + chunk) for lo = 0, chunk, ..."""
    n_threads = max(1, int(numba.get_num_threads()))
    return max(min_chunk, -(-n_items // (n_threads * CHUNKS_PER_THREAD)), 1)


def parallel_for(kernel, n_items: int, *args, min_chunk: int = 1) -> None:
    """Run ``kernel(lo, hi, *args)`` over [0, n_items) in chunks on numba.get_num_threads() threads."""
    n_threads = max(1, int(numba.get_num_threads()))
    chunk = chunk_length(n_items, min_chunk)
    bounds = [(lo, min(n_items, lo + chunk)) for lo in range(0, n_items, chunk)]
    if n_threads == 1 or len(bounds) <= 1:
        kernel(0, n_items, *args)
        return
    futures = [_executor(n_threads).submit(kernel, lo, hi, *args) for lo, hi in bounds]
    for f in futures:
        f.result()


def parallel_bands(kernel, n_items: int, *args) -> None:
    """``kernel(lo, hi, *args)`` over [0, n_items) in one band per thread: for kernels whose every
    call scans a whole shared input (the tile lists, the per-Gaussian reduction) and keeps only
    what falls in its band, so more bands than threads would only repeat the scan."""
    n_threads = max(1, int(numba.get_num_threads()))
    parallel_for(kernel, n_items, *args, min_chunk=max(1, -(-n_items // n_threads)))


def depth_order(idx, depths) -> np.ndarray:
    """``idx[np.argsort(depths[idx], kind="stable")]`` (RAS-02: by depth, ties by index; idx
    ascending).  Finite depths are sorted by refgs.fast.tiles.radix_argsort on their bits, turned
    into unsigned integers of the same order (sign bit flipped for positive numbers, every bit for
    negative ones; -0 taken as +0): the same stable order as numpy's, in O(n) (numpy's stable
    sort of floats is a merge sort).  Non-finite depths: numpy's argsort."""
    keys = depths[idx]
    if keys.dtype not in (np.float32, np.float64) or not np.all(np.isfinite(keys)):
        return idx[np.argsort(keys, kind="stable")]
    keys = keys + keys.dtype.type(0)                    # -0 -> +0: equal depths, equal keys
    nbits = 8 * keys.itemsize
    bits = keys.view(np.int32 if nbits == 32 else np.int64).astype(np.int64)
    sign = np.int64(1) << (nbits - 1)
    low = (np.int64(1) << nbits) - 1 if nbits < 64 else np.int64(-1)
    sortable = np.where(bits & sign, ~bits, bits | sign) & low
    return idx[tl.radix_argsort(sortable, nbits)]


def _every_intersection(order, rect):
    """(rect_off, live) of the full lists: every tile of every rectangle live."""
    rect_off = np.empty(order.size + 1, np.int64)
    tl.rect_offsets(order, rect, rect_off)
    return rect_off, np.ones(int(rect_off[-1]), np.bool_)


def live_intersections(order, rect, means2d, conics, opac, eps: float, screen: bool = True,
                       rect_s=None):
    """(rect_off (V+1,) int64, live (P_full,) bool): for each visible Gaussian order[k] and each
    tile of its rectangle (row-major, from rect_off[k]) whether the screen may keep it in some
    pixel row there (refgs.fast.tiles.tile_alive, conservative, per Gaussian on the threads);
    all True without the screen (``screen=False``: the spec's full lists).  ``rect_s``:
    rect[order] (refgs.fast.tiles.rects_in_order) if the caller has it."""
    rect_off, live = _every_intersection(order, rect)
    if not screen:
        return rect_off, live
    if rect_s is None:
        rect_s = tl.rects_in_order(order, rect)
    scr = np.empty((order.size, 6), np.float64)
    parallel_for(tl.screen_inputs, order.size, order, means2d, conics, opac, scr,
                 min_chunk=MIN_GAUSSIAN_CHUNK)
    parallel_for(tl.tile_alive, order.size, rect_s, rect_off, scr, float(eps), live,
                 min_chunk=MIN_GAUSSIAN_CHUNK // 8)
    return rect_off, live


def build_tile_lists(order, rect, gx: int, gy: int, rect_off=None, live=None, rect_s=None):
    """refgs.fast.tiles.build_tile_lists (RAS-01, RAS-02) with both passes over chunks of the
    Gaussians in depth order on the threads: each chunk counts its own entries per tile, and
    its entries of a tile are placed after those of the chunks before (tiles.chunk_starts), so
    the lists are the sequential ones.  ``rect_off``/``live`` from :func:`live_intersections`
    (default: every intersection, the full lists), ``rect_s`` = rect[order] if the caller has it.
    Returns (gauss (P,) int64, offsets (gx gy + 1,) int64, pos (P,) int32: each entry's position
    in its tile's full list)."""
    if live is None:
        rect_off, live = _every_intersection(order, rect)
    V, n_tiles = order.size, gx * gy
    if rect_s is None:
        rect_s = tl.rects_in_order(order, rect)
    n_threads = max(1, int(numba.get_num_threads()))
    chunk = chunk_length(V, max(MIN_LIST_CHUNK, -(-V // n_threads)))    # one chunk per thread
    n_chunks = max(1, -(-V // chunk))
    counts = np.zeros((n_chunks, n_tiles), np.int64)
    full = np.zeros((n_chunks, n_tiles), np.int64)
    parallel_for(tl.tile_counts, V, chunk, rect_s, rect_off, live, gx, counts, full,
                 min_chunk=chunk)
    offsets = np.zeros(n_tiles + 1, np.int64)
    np.cumsum(counts.sum(axis=0), out=offsets[1:])
    cursor, full_start = tl.chunk_starts(counts, full, offsets)
    gauss = np.empty(int(offsets[-1]), np.int64)
    pos = np.empty(int(offsets[-1]), np.int32)
    parallel_for(tl.tile_fill, V, chunk, order, rect_s, rect_off, live, gx, cursor, full_start,
                 gauss, pos, min_chunk=chunk)
    return gauss, offsets, pos


def input_error(field: str, expected: str, got) -> None:
    """ValueError naming ``field`` and what was expected (the reference's message form)."""
    raise ValueError(f"{field}: expected {expected}, got {got}")


def check_cotangent(name: str, v, shape, dt):
    """None, or ``v`` as a finite array of ``shape`` in ``dt`` (ValueError naming ``name``
    otherwise; the checks of refgs.render.render_backward)."""
    if v is None:
        return None
    v = np.asarray(v)
    if v.shape != shape or not np.all(np.isfinite(v)):
        input_error(name, f"finite values of shape {shape}", v.shape)
    return v.astype(dt, copy=False)


def _c(a, dt):
    return np.ascontiguousarray(a, dtype=dt)


def _raster_constants(dt, profile) -> np.ndarray:
    rc = np.zeros(rk.N_RASTER_CONSTANTS, np.float64)
    rc[rk.R_ONE], rc[rk.R_NEG_HALF] = 1.0, -0.5
    rc[rk.R_CAP], rc[rk.R_ALPHA_MIN], rc[rk.R_T_MIN] = profile.alpha_max, ALPHA_MIN, T_MIN
    return rc.astype(dt)


def render(gaussians, camera, config: RenderConfig | None = None, *,
           screen: bool = True, geometry: str = "input") -> RenderOutput:
    """Render like :func:`refgs.render` (same RenderOutput fields and meanings, API-04).

    The ``cache`` holds what :func:`render_backward` needs (compiled-kernel inputs, tile lists).
    ``screen=False`` switches off the conservative per-row candidate screen of
    refgs.fast.tiles (every pixel x list-slot pair evaluated; bit-identical results, slower;
    for tests).  ``geometry``: one of GEOMETRY_PRECISIONS, the precision of the per-Gaussian
    stage for float32 Gaussians (outputs are float32 either way).
    """
    config = RenderConfig() if config is None else config
    validate_inputs(gaussians, camera, config)
    if geometry not in GEOMETRY_PRECISIONS:
        input_error("geometry", f"one of {GEOMETRY_PRECISIONS}", geometry)
    if config.deviations:
        input_error("config.deviations", "none (refgs.fast renders the two profiles; the named "
                    "deviations of docs/spec/deviations.md are refgs.render's)",
                    sorted(config.deviations))
    profile = resolve_profile(config)
    g = gaussians
    out_dt = g.means.dtype                      # compositing and outputs
    dt = np.dtype(np.float64) if geometry == "float64" else out_dt   # the per-Gaussian stage
    n = len(g)
    W, H = int(camera.width), int(camera.height)
    deg = config.active_sh_degree(g.sh.shape[1])
    means, log_scales, quats = _c(g.means, dt), _c(g.log_scales, dt), _c(g.quats, dt)
    # SH coefficients (48 of a Gaussian's 59 numbers) stay in the Gaussians' dtype: the kernels
    # multiply them by per-Gaussian values of the stage's dtype, so a float32 coefficient enters
    # float64 arithmetic exactly as its cast would, without a float64 copy of the array
    logits, sh = _c(g.opacity_logits, dt), _c(g.sh, out_dt)
    oscale = np.ones(n, dt) if config.opacity_scale is None else _c(config.opacity_scale, dt)
    w2c = _c(camera.world_to_camera, dt)
    campos = camera.center.astype(dt)
    cst = gk.constants_array(dt, profile, camera, frustum_limits(camera, profile, np.dtype(dt)))
    flags = gk.flags_array(profile, config.antialiased, deg, W, H)

    means2d, cov2d, conics = np.empty((n, 2), dt), np.empty((n, 3), dt), np.empty((n, 3), dt)
    depths, comp, o_sig, opac = (np.empty(n, dt) for _ in range(4))
    colors, clamped = np.empty((n, 3), dt), np.empty((n, 3), np.bool_)
    radii, visible, rect = np.empty((n, 2), np.int32), np.empty(n, np.bool_), np.empty((n, 4), np.int64)
    parallel_for(gk.gaussians_forward, n, means, log_scales, quats, logits, oscale, sh, w2c, campos,
                 cst, float(profile.radius_sigma), flags, means2d, depths, cov2d, conics, comp,
                 o_sig, opac, colors, clamped, radii, visible, rect, min_chunk=MIN_GAUSSIAN_CHUNK)

    gx, gy = tile_grid(W, H)
    order = depth_order(np.flatnonzero(visible), depths)          # RAS-02: depth, ties by index

    conics_g = conics                              # the per-Gaussian stage's, for the backward
    # the compositing kernels read the 2D means in the geometry's precision: a float64 mean is
    # carried there as float32 value + float32 residual (refgs.fast.tiles.gather), so pixel
    # offsets keep float64's position (docs/fast.md, "Mixed precision")
    means2d_c = means2d
    if out_dt != dt:                               # float32 compositing of float64 geometry
        means2d, cov2d, conics = means2d.astype(out_dt), cov2d.astype(out_dt), conics.astype(out_dt)
        depths, opac, colors = depths.astype(out_dt), opac.astype(out_dt), colors.astype(out_dt)
    dt = out_dt
    eps = float(np.finfo(dt).eps)
    # the tile lists keep only the Gaussians the screen keeps in some row of a tile (live
    # intersections; module docstring of refgs.fast.tiles), n_contrib still counts full lists
    rect_s = tl.rects_in_order(order, rect)                       # rect[order]
    rect_off, live = live_intersections(order, rect, means2d_c, conics, opac, eps, screen, rect_s)
    gauss, offsets, pos = build_tile_lists(order, rect, gx, gy, rect_off, live, rect_s)
    longest = int(np.max(np.diff(offsets))) if offsets.size > 1 else 0
    if longest > rk.MAX_LIST_LENGTH[np.dtype(dt)]:       # the kernels count slots in dt
        input_error("gaussians", f"at most {rk.MAX_LIST_LENGTH[np.dtype(dt)]} Gaussians on one "
                    f"tile for {np.dtype(dt).name} compositing (render in float64)", longest)
    bg = np.asarray(config.background, dt)
    rc = _raster_constants(dt, profile)
    image = np.empty((H, W, 3), dt)
    alpha, depth, final_T = np.empty((H, W), dt), np.empty((H, W), dt), np.empty((H, W), dt)
    n_contrib, last = np.empty((H, W), np.int32), np.empty((H, W), np.int32)
    row_mask = np.empty(gauss.size, np.int64)
    forward = rk.COMPOSITING_KERNELS[np.dtype(dt)][0]
    parallel_for(forward, gx * gy, gauss, offsets, pos, means2d_c, conics, opac, colors,
                 depths, bg, rc, eps, bool(profile.stop_inclusive), bool(screen), gx, image, alpha,
                 depth, n_contrib, last, final_T, row_mask)
    cache = {"tag": CACHE_TAG, "profile": profile, "sh_degree": deg,
             "lists": {"gauss": gauss, "offsets": offsets, "pos": pos,
                       "full_size": int(live.size)},
             "tile_rect": rect, "last": last, "row_mask": row_mask,
             "arrays": (means, log_scales, quats, logits, oscale, sh, w2c, campos),
             "cst": cst, "flags": flags, "rc": rc, "bg": bg, "screen": bool(screen),
             "comp": comp, "o_sig": o_sig, "clamped": clamped, "scale": oscale,
             "conics_geometry": conics_g, "means2d_compositing": means2d_c, "geometry": geometry}
    return RenderOutput(image=image, alpha=alpha, depth=depth, n_contrib=n_contrib, radii=radii,
                        means2d=means2d, depths=depths, conics=conics, cov2d=cov2d, colors=colors,
                        opacities=opac, final_T=final_T, visible=visible, gaussians=g,
                        camera=camera, config=config, cache=cache)


def render_backward(out: RenderOutput, v_image, v_alpha=None, v_depth=None) -> Gradients:
    """Gradients like :func:`refgs.render_backward` (API-05) for an output of :func:`render`.

    v_image (H,W,3), optional v_alpha (H,W) and v_depth (H,W).  Returns refgs.Gradients in the
    dtype of ``out`` (means2d = dL/d 2D mean in pixels; culled Gaussians get zero rows).
    """
    if not isinstance(out, RenderOutput) or out.cache.get("tag") != CACHE_TAG:
        input_error("out", "the RenderOutput of refgs.fast.render", type(out).__name__)
    c = out.cache
    dt = out.image.dtype
    H, W = out.alpha.shape
    v_image = check_cotangent("v_image", v_image, (H, W, 3), dt)
    if v_image is None:
        input_error("v_image", f"an array of shape {(H, W, 3)}", None)
    v_alpha = check_cotangent("v_alpha", v_alpha, (H, W), dt)
    v_depth = check_cotangent("v_depth", v_depth, (H, W), dt)
    v_alpha = np.zeros((H, W), dt) if v_alpha is None else _c(v_alpha, dt)
    v_depth = np.zeros((H, W), dt) if v_depth is None else _c(v_depth, dt)
    v_image = _c(v_image, dt)
    profile = c["profile"]
    gauss, offsets = c["lists"]["gauss"], c["lists"]["offsets"]
    gx, gy = tile_grid(W, H)
    n = out.means2d.shape[0]

    contrib = np.empty((gauss.size, rk.N_GRAD_COLUMNS), dt)
    backward = rk.COMPOSITING_KERNELS[np.dtype(dt)][1]
    parallel_for(backward, gx * gy, gauss, offsets, c["means2d_compositing"], out.conics,
                 out.opacities, out.colors, out.depths, c["bg"], c["rc"],
                 bool(profile.grad_through_alpha_cap), gx, c["last"], out.final_T,
                 v_image, v_alpha, v_depth, c["row_mask"], contrib)
    means, log_scales, quats, logits, oscale, sh, w2c, campos = c["arrays"]
    gdt = means.dtype                       # the per-Gaussian stage's precision (render geometry)
    per_g = np.empty((n, rk.N_GRAD_COLUMNS), gdt)
    parallel_bands(rk.reduce_by_gaussian, n, gauss, contrib, per_g)   # culled rows stay 0
    # the gradients in the output dtype directly (each entry stored once by the kernel, so a
    # float32 output of float64 geometry is rounded once, as a cast of the float64 result)
    o_means, o_ls, o_quats = np.empty((n, 3), dt), np.empty((n, 3), dt), np.empty((n, 4), dt)
    o_logits, o_sh = np.empty(n, dt), np.empty(sh.shape, dt)
    parallel_for(gk.gaussians_backward, n, means, log_scales, quats, logits, oscale, sh, w2c,
                 c["cst"], c["flags"], campos, c["conics_geometry"], c["comp"], c["o_sig"],
                 c["clamped"], out.visible, per_g, o_means, o_ls, o_quats, o_logits, o_sh,
                 min_chunk=MIN_GAUSSIAN_CHUNK)
    return Gradients(means=o_means, log_scales=o_ls, quats=o_quats, opacity_logits=o_logits,
                     sh=o_sh, means2d=per_g[:, rk.G_MX:rk.G_MY + 1].astype(dt))
