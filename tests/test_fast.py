"""refgs.fast (numba backend, issue 7) against the float64 reference.

Tolerances (docs/fast.md):

* fast float64 vs refgs float64: image / alpha / depth / final_T / per-Gaussian outputs within
  1e-12 (absolute; the values are O(1) .. O(10)), n_contrib, radii and visible exactly equal,
  every gradient field within 1e-10 relative L2 error.  Both compute the same operations; they
  differ only in summation order and libm vs numpy exp (a few ulp).
* fast float32 vs refgs float64: image and alpha within 1e-5 absolute, depth within 1e-5 relative
  to the largest depth, except at the near-tie pixels that refgs.fast.ties finds (counted, and
  bounded here at a few percent of the image); every gradient field within 1e-4 relative L2 with
  the cotangent zeroed on the near-tie pixels and the kink-tied Gaussians' rows left out.

The quaternion gradient of an isotropic Gaussian is exactly 0 in exact arithmetic and rounding
noise in both implementations, so its relative error is taken against at least
QUAT_COMPANION_FLOOR times the log-scale gradient's norm.  Needles (2D condition number above
COND_LIMIT) amplify rounding by ~cond^2 in any two float64 implementations; their gradient rows
are checked one by one against ILL_COND_RTOL cond^2.
"""
from __future__ import annotations

import importlib
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings

numba = pytest.importorskip("numba")

import refgs  # noqa: E402
import refgs.fast as fast  # noqa: E402
from refgs import Camera, Gaussians, RenderConfig  # noqa: E402
from refgs.fast.ties import FLOAT32_BANDS, GEOMETRY64_BANDS, find_ties  # noqa: E402
from refgs.synthetic import benchmark_scene  # noqa: E402

from strategies import (make_camera, max_examples, place_gaussians,  # noqa: E402
                        random_cotangents, scenes)

#: fast float64 vs reference float64
F64_ATOL = 1e-12
F64_GRAD_REL_L2 = 1e-10
#: fast float32 vs reference float64 (outside near-ties)
F32_ATOL = 1e-5
F32_GRAD_REL_L2 = 1e-4
#: at most this fraction of the pixels may be near-ties in the float32 checks
F32_MAX_TIE_FRACTION = 0.05
PIXEL_FIELDS = ("image", "alpha", "depth", "final_T")
GAUSSIAN_FIELDS = ("means2d", "depths", "conics", "cov2d", "colors", "opacities")
GRAD_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh", "means2d")


#: Gaussians whose 2D covariance has condition (ac + b^2) / (ac - b^2) above this (needles) have
#: gradients that amplify rounding by ~cond^2 in any implementation: their rows are checked one
#: by one against ILL_COND_RTOL * cond^2 relative instead of the field-wise 1e-10
COND_LIMIT = 100.0
ILL_COND_RTOL = 1e-14
#: the quaternion gradient of an (almost) isotropic Gaussian is rounding noise; it is judged
#: against this fraction of the log-scale gradient (its natural companion size) as a floor
QUAT_COMPANION_FLOOR = 1e-3


def rel_l2(a, b, floor: float = 0.0) -> float:
    """||a - b|| / max(||b||, floor) (0 when both are 0)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    den = max(float(np.linalg.norm(b)), floor)
    return float(np.linalg.norm(a - b) / den) if den > 0 else float(np.linalg.norm(a))


def grad_rel_l2(got, ref, k: str, rows=slice(None)) -> float:
    """Relative L2 error of gradient field k (quats floored by the log-scale gradient)."""
    floor = QUAT_COMPANION_FLOOR * float(np.linalg.norm(ref.log_scales[rows])) if k == "quats" else 0.0
    return rel_l2(getattr(got, k)[rows], getattr(ref, k)[rows], floor)


def assert_f64_match(g, cam, cfg, seed=0):
    """fast float64 == reference float64 (module docstring), forward and backward."""
    ref = refgs.render(g, cam, cfg)
    out = fast.render(g, cam, cfg)
    for k in PIXEL_FIELDS:
        np.testing.assert_allclose(getattr(out, k), getattr(ref, k), rtol=0, atol=F64_ATOL, err_msg=k)
    vis = ref.visible
    np.testing.assert_array_equal(out.visible, vis)
    np.testing.assert_array_equal(out.radii, ref.radii)
    np.testing.assert_array_equal(out.n_contrib, ref.n_contrib)
    for k in GAUSSIAN_FIELDS:
        a, b = getattr(out, k)[vis], getattr(ref, k)[vis]
        rtol = F64_ATOL
        if k == "conics":       # conic = adj / det: det = a c - b^2 cancels for needles
            ca, cb, cc = (ref.cov2d[vis, q] for q in range(3))
            rtol = F64_ATOL * (1 + (ca * cc + cb * cb) / (ca * cc - cb * cb))[:, None]
        assert np.all(np.abs(a - b) <= rtol * np.abs(b) + F64_ATOL), k
    ca, cb, cc = (ref.cov2d[:, q] for q in range(3))
    with np.errstate(all="ignore"):
        cond = np.where(vis, (ca * cc + cb * cb) / (ca * cc - cb * cb), 1.0)
    good = cond <= COND_LIMIT
    H, W = ref.alpha.shape
    cot = random_cotangents(np.random.default_rng(seed), H, W)
    gr = refgs.render_backward(ref, **cot)
    gf = fast.render_backward(out, **cot)
    for k in GRAD_FIELDS:
        a, b = getattr(gf, k), getattr(gr, k)
        assert a.shape == b.shape and a.dtype == np.float64, k
        assert np.all(np.isfinite(a)), k
        assert not np.any(a[~vis]), k                    # culled Gaussians: exactly zero rows
        if k == "means2d":
            continue                                      # checked with means below
        err = grad_rel_l2(gf, gr, k, good)
        assert err <= F64_GRAD_REL_L2, (k, err)
        for row in np.flatnonzero(~good):                 # needles: per row, scaled by cond^2
            den = max(np.abs(b[row]).max(), QUAT_COMPANION_FLOOR * np.abs(gr.log_scales[row]).max()
                      if k == "quats" else 0.0)
            assert np.abs(a[row] - b[row]).max() <= ILL_COND_RTOL * cond[row] ** 2 * den, (k, row)
    assert grad_rel_l2(gf, gr, "means2d", good) <= F64_GRAD_REL_L2
    return ref, out


# ---------------------------------------------------------------------------------------------
# float64: equal to the reference
# ---------------------------------------------------------------------------------------------

@settings(max_examples=max_examples(12))
@given(scene=scenes(n=(1, 8), width=(16, 48), height=(12, 40)))
def test_f64_matches_reference_random_scenes(scene):
    assert_f64_match(scene.gaussians, scene.camera, scene.config, scene.seed % 1000)


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_f64_opaque_stack(profile):
    """HARD-07: 20 nearly opaque Gaussians stacked on one spot: the stop rule cuts each pixel
    before the end of its list; the saturating Gaussian is not blended."""
    cam = Camera.look_at((0, 0, -4.0), (0, 0, 0), fx=30, width=40, height=32)
    rng = np.random.default_rng(3)
    n = 20
    t_cam = np.stack([rng.normal(0, 0.05, n), rng.normal(0, 0.05, n), np.linspace(3.0, 5.0, n)], -1)
    means = (t_cam - cam.translation) @ cam.rotation
    g = Gaussians(means, np.log(0.4) + rng.uniform(-0.4, 0.4, (n, 3)), rng.normal(size=(n, 4)),
                  np.full(n, 6.0), rng.normal(0, 0.5, (n, 4, 3)))
    _, out = assert_f64_match(g, cam, RenderConfig(profile=profile))
    i, j = cam.height // 2, cam.width // 2                # the stack's centre
    tile = (i // 16) * refgs.rasterize.tile_grid(cam.width, cam.height)[0] + j // 16
    length = int(np.diff(out.cache["lists"]["offsets"])[tile])
    assert length == n and 0 < out.n_contrib[i, j] < n // 2   # cut off early in the list
    assert out.final_T[i, j] < 1e-3


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_tile_lists_longer_than_the_slot_counter_are_refused(monkeypatch, dtype):
    """The kernels count list slots in the compositing dtype (exact up to MAX_LIST_LENGTH, 2**24
    in float32); render refuses a longer tile list with a ValueError naming ``gaussians``.  The
    limit is lowered here to the 20 Gaussians stacked on one tile."""
    kernels = importlib.import_module("refgs.fast.kernels")
    assert kernels.MAX_LIST_LENGTH[np.dtype(np.float32)] == 2 ** 24
    cam = Camera.look_at((0, 0, -4.0), (0, 0, 0), fx=30, width=40, height=32)
    n = 20
    t_cam = np.stack([np.zeros(n), np.zeros(n), np.linspace(3.0, 5.0, n)], -1)
    g = Gaussians((t_cam - cam.translation) @ cam.rotation, np.full((n, 3), np.log(0.4)),
                  np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 2.0), np.zeros((n, 1, 3))).astype(dtype)
    monkeypatch.setattr(kernels, "MAX_LIST_LENGTH", {np.dtype(dtype): n})
    assert fast.render(g, cam).n_contrib.max() > 0                  # 20 entries: at the limit
    monkeypatch.setattr(kernels, "MAX_LIST_LENGTH", {np.dtype(dtype): n - 1})
    with pytest.raises(ValueError, match="gaussians: expected at most 19 Gaussians on one tile"):
        fast.render(g, cam)


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_f64_equal_depths_ordered_by_index(profile):
    """RAS-02: Gaussians at exactly the same depth composite in index order."""
    K = np.array([[20.0, 0, 16], [0, 20.0, 12], [0, 0, 1]])
    cam = Camera(np.eye(4), K, 32, 24)
    rng = np.random.default_rng(11)
    n = 8
    means = np.stack([rng.normal(0, 0.1, n), rng.normal(0, 0.1, n), np.full(n, 2.0)], -1)
    rgb = np.eye(3)[np.arange(n) % 3]
    sh = ((rgb - 0.5) / refgs.constants.SH_C0)[:, None, :]
    g = Gaussians(means, np.log(0.15) + rng.uniform(-0.3, 0.3, (n, 3)), rng.normal(size=(n, 4)),
                  np.full(n, 1.5), sh)
    _, out = assert_f64_match(g, cam, RenderConfig(profile=profile))
    flipped = fast.render(g.subset(np.arange(n)[::-1]), cam, RenderConfig(profile=profile))
    assert np.max(np.abs(flipped.image - out.image)) > 1e-3      # the order matters here


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_f64_offscreen_behind_and_near(profile):
    """Gaussians beyond every edge, behind the camera, at the near plane and just past it."""
    cam = Camera.look_at((0, 0, -4.0), (0, 0, 0), fx=25, width=37, height=29, cx=17.3, cy=15.1)
    rng = np.random.default_rng(5)
    g = place_gaussians(rng, cam, 30, offscreen=0.6, sh_degree=2)
    t = np.array([[0.0, 0.0, -1.0], [0.1, 0.0, 0.2], [0.0, 0.1, 0.2000001], [0.0, 0.0, 0.01],
                  [0.3, -0.2, 0.35]])
    extra = Gaussians((t - cam.translation) @ cam.rotation, np.full((5, 3), -2.5),
                      rng.normal(size=(5, 4)), np.zeros(5), rng.normal(0, 0.3, (5, 9, 3)))
    g = Gaussians(*(np.concatenate([getattr(g, f), getattr(extra, f)]) for f in Gaussians.FIELDS))
    assert_f64_match(g, cam, RenderConfig(profile=profile, background=(0.2, 0.5, 0.9)))


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_f64_huge_splats_and_needles(profile):
    """HARD-11 / HARD-02: splats covering every tile near the camera, and needles (one axis
    1e3 times the others) across the image."""
    cam = Camera.look_at((0, 0, -4.0), (0, 0, 0), fx=30, width=45, height=33)
    rng = np.random.default_rng(7)
    g = place_gaussians(rng, cam, 10, sh_degree=1)
    t = np.array([[0.0, 0.0, 0.5], [0.2, -0.1, 1.0], [0.0, 0.0, 3.0], [0.5, 0.3, 2.0]])
    ls = np.array([[1.5, 1.2, 1.0], [2.0, 2.0, 2.0], [np.log(0.01), np.log(10.0), np.log(0.01)],
                   [np.log(8.0), np.log(0.005), np.log(0.005)]])
    big = Gaussians((t - cam.translation) @ cam.rotation, ls, rng.normal(size=(4, 4)),
                    np.full(4, 0.5), rng.normal(0, 0.3, (4, 4, 3)))
    g = Gaussians(*(np.concatenate([getattr(g, f), getattr(big, f)]) for f in Gaussians.FIELDS))
    _, out = assert_f64_match(g, cam, RenderConfig(profile=profile))
    gx, gy = refgs.rasterize.tile_grid(cam.width, cam.height)
    rect = out.cache["tile_rect"]
    full = (rect[:, 1] - rect[:, 0]) * (rect[:, 3] - rect[:, 2]) == gx * gy
    assert full.sum() >= 1                                # some splat covers every tile


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_huge_splats_at_the_near_plane(profile, dtype):
    """HARD-11: scales up to e^25 (e^21 in float32) just past the near plane cover every tile;
    radii saturate at the int32 maximum, nothing overflows; float64 equals the reference."""
    K = np.array([[100.0, 0, 64], [0, 100.0, 64], [0, 0, 1]])
    cam = Camera(np.eye(4), K, 128, 128)
    n = 12
    rng = np.random.default_rng(11)
    z = refgs.get_profile(profile).near * rng.uniform(1.05, 1.5, n)
    means = np.stack([rng.uniform(-0.5, 0.5, n) * z, rng.uniform(-0.5, 0.5, n) * z, z], -1)
    ls = np.log(rng.uniform(1e2, 1e4, (n, 3)))
    ls[0] = 20.0
    ls[1] = 25.0 if dtype == np.float64 else 21.0
    g = Gaussians(means, ls, rng.normal(size=(n, 4)), rng.uniform(-3, -1, n),
                  rng.normal(0, 0.3, (n, 1, 3))).astype(dtype)
    cfg = RenderConfig(profile=profile)
    if dtype == np.float64:
        _, out = assert_f64_match(g, cam, cfg)
    else:
        out = fast.render(g, cam, cfg)                    # float32 radii ~1e7: rounding-level
        np.testing.assert_allclose(out.radii, refgs.render(g, cam, cfg).radii, rtol=1e-6)
    assert out.visible.all() and int(out.cache["lists"]["offsets"][-1]) == n * 64
    assert out.radii[0].tolist() == out.radii[1].tolist() == [np.iinfo(np.int32).max] * 2
    grads = fast.render_backward(out, np.ones((128, 128, 3)))
    assert np.all(np.isfinite(out.image)) and np.all(np.isfinite(out.alpha))
    for k in GRAD_FIELDS:
        assert np.all(np.isfinite(getattr(grads, k))), k


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_f64_empty_and_all_culled(profile):
    """API-06: no Gaussians, or every Gaussian behind the camera: background, zero gradients."""
    cam = Camera.look_at((0, 0, -4.0), (0, 0, 0), fx=25, width=20, height=17)
    cfg = RenderConfig(profile=profile, background=(0.1, 0.2, 0.3))
    for g in (Gaussians.empty(k=4),
              Gaussians(np.array([[0.0, 0.0, -6.0]]), np.zeros((1, 3)), np.array([[1.0, 0, 0, 0]]),
                        np.zeros(1), np.zeros((1, 4, 3)))):
        _, out = assert_f64_match(g, cam, cfg)
        np.testing.assert_array_equal(out.image, np.broadcast_to([0.1, 0.2, 0.3], out.image.shape))
        assert not out.n_contrib.any() and np.all(out.final_T == 1)
        grads = fast.render_backward(out, np.ones(out.image.shape))
        for k in GRAD_FIELDS:
            assert not np.any(getattr(grads, k)), k


def test_screen_is_exact():
    """The per-row candidate screen changes nothing: bit-identical to evaluating every pair."""
    g, cam = benchmark_scene(600, 96, 80, seed=3)
    for dt in (np.float64, np.float32):
        for profile in ("inria", "gsplat"):
            cfg = RenderConfig(profile=profile, antialiased=profile == "gsplat")
            a = fast.render(g.astype(dt), cam, cfg)
            b = fast.render(g.astype(dt), cam, cfg, screen=False)
            for k in ("image", "alpha", "depth", "final_T", "n_contrib"):
                np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
            v = np.random.default_rng(0).normal(size=a.image.shape)
            ga, gb = fast.render_backward(a, v), fast.render_backward(b, v)
            for k in GRAD_FIELDS:
                np.testing.assert_array_equal(getattr(ga, k), getattr(gb, k), err_msg=k)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_screen_slots_is_slot_rows(dtype):
    """refgs.fast.tiles.screen_slots (the screen across a tile's slots, in SIMD lanes) gives
    slot_rows' mask for every slot, bit for bit: slots inside, across and outside the tile, at
    its edges, opacities around 1/255 and 0, odd conics (negative, zero determinant, NaN, inf),
    non-finite means, and with the screen switched off."""
    from refgs.fast import tiles as tl
    rng = np.random.default_rng(5)
    n = 4000
    tab = np.zeros((n, tl.N_TAB), dtype)
    x0, y0 = 32.5, 16.5                                 # the tile at (2, 1)
    tab[:, 0] = x0 - 6 + rng.uniform(0, 28, n)          # means around the tile
    tab[:, 1] = y0 - 6 + rng.uniform(0, 28, n)
    tab[::7, 0] = x0 + rng.integers(-1, 17, tab[::7].shape[0])   # on pixel centres' grid
    ang, a, b = rng.uniform(0, np.pi, n), 10.0 ** rng.uniform(-3, 1, n), 10.0 ** rng.uniform(-3, 1, n)
    c, s_ = np.cos(ang), np.sin(ang)
    tab[:, 2] = c * c * a + s_ * s_ * b                  # positive-definite conics, elongated
    tab[:, 3] = c * s_ * (a - b)
    tab[:, 4] = s_ * s_ * a + c * c * b
    tab[:, 5] = 10.0 ** rng.uniform(-3, 0, n)           # opacities around 1/255
    tab[::11, 5] = 0.0
    tab[::13, 5] = 1.0 / 255.0
    tab[1::17, 2] = -tab[1::17, 2]                      # odd conics
    tab[2::19, 3] = np.sqrt(np.abs(tab[2::19, 2] * tab[2::19, 4]))   # det ~ 0
    tab[3::23, 4] = np.nan
    tab[4::29, 2] = np.inf
    tab[5::31, 0] = np.nan
    tab[6::37, 1] = -np.inf
    tab[:, 10] = rng.normal(0, 1e-6, n)                 # residuals of a float64 mean
    tab[::2, 10:] = 0.0
    ys = (y0 + np.arange(16)).astype(dtype)
    eps = float(np.finfo(dtype).eps)
    scr = np.empty((tl.N_SCREEN_ROWS, n))
    for screen in (True, False):
        got = np.empty(n, np.int64)
        tl.screen_slots(tab, n, x0, x0 + 15, y0, y0 + 15, ys, eps, screen, scr, got)
        want = np.array([tl.slot_rows(tab, k, x0, x0 + 15, y0, y0 + 15, ys, eps, screen)
                         for k in range(n)])
        np.testing.assert_array_equal(got, want)
        if screen:                              # every kind of verdict occurred
            assert (want == 0).any() and (want == 2 ** 32 - 1).any()
            assert ((want != 0) & (want != 2 ** 32 - 1)).sum() > n // 10


def _needles(n, seed):
    """Elongated, rotated Gaussians of every opacity around the 1/255 threshold (logits from
    -8 to 4: o from 3e-4 to 0.98) in front of a 96x80 camera."""
    rng = np.random.default_rng(seed)
    cam = Camera.look_at((0, 0, -4.0), (0, 0, 0), fx=90, width=96, height=80)
    ls = np.log(rng.uniform(0.005, 0.05, (n, 3)))
    ls[:, 0] += np.log(rng.uniform(1, 150, n))                     # axis ratios up to 150
    g = Gaussians(rng.uniform(-1.5, 1.5, (n, 3)) * [1, 0.9, 0.5], ls, rng.normal(size=(n, 4)),
                  rng.uniform(-8, 4, n), rng.normal(size=(n, 1, 3)) * 0.5)
    return g, cam


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_live_intersections_contain_every_slot_the_screen_keeps(dtype):
    """refgs.fast.tiles.tile_alive is conservative: every (tile, slot) that the screen keeps in
    some pixel row of the full tile lists is live, so the live lists change no output
    (test_screen_is_exact); and it is tight: few live slots are not kept."""
    from refgs.fast import tiles as tl
    from refgs.fast.render import live_intersections
    for seed in range(3):
        g, cam = _needles(400, seed) if seed else benchmark_scene(600, 96, 80, seed=3)
        g = g.astype(dtype)
        full = fast.render(g, cam, screen=False)         # full lists, rows unscreened
        c = full.cache
        order = np.flatnonzero(full.visible)[np.argsort(full.depths[full.visible], kind="stable")]
        eps = float(np.finfo(dtype).eps)
        rect_off, live = live_intersections(order, c["tile_rect"], full.means2d, full.conics,
                                            full.opacities, eps)
        H, W = full.alpha.shape
        gx, n_tiles = -(-W // 16), c["lists"]["offsets"].size - 1
        gauss, offsets, pos = tl.build_tile_lists(order, c["tile_rect"], n_tiles, gx, rect_off,
                                                  np.ones(live.size, np.bool_))
        assert np.array_equal(gauss, c["lists"]["gauss"])     # the full lists, in depth order
        # the slots the exact screen keeps in some row of the full lists (refgs.fast.tiles.chords)
        dt = np.dtype(dtype)
        where = {int(gi): k for k, gi in enumerate(order)}
        kept = 0
        for t in range(n_tiles):
            a, L = offsets[t], offsets[t + 1] - offsets[t]
            if L == 0:
                continue
            ty, tx = divmod(t, gx)
            tab = np.empty((L, tl.N_TAB), dt)
            tl.gather(gauss, a, L, full.means2d, full.conics, full.opacities, full.colors,
                      full.depths, tab)
            xs, ys = tl.centres(tx * 16, tab), tl.centres(ty * 16, tab)
            cnt, rs = np.empty(16, np.int64), np.empty((16, L), np.int32)
            col = np.empty((16, L), np.int8), np.empty((16, L), np.int8)
            tl.chords(tab, L, xs, ys, eps, True, cnt, rs, *col)
            for s in {int(x) for r in range(16) for x in rs[r, :cnt[r]]}:
                gi = int(gauss[a + s])
                k = where[gi]
                x0, x1, y0, _ = c["tile_rect"][gi]
                kept += 1
                assert live[rect_off[k] + (ty - y0) * (x1 - x0) + (tx - x0)], (seed, t, s)
        live_kept = int(live.sum())
        assert kept <= live_kept <= 1.1 * kept + 10, (kept, live_kept)


# ---------------------------------------------------------------------------------------------
# float32 against the float64 reference
# ---------------------------------------------------------------------------------------------

def check_f32(g64, cam, cfg, seed=0, geometry="input") -> dict:
    """fast float32 vs reference float64 outside near-ties (module docstring); returns counts.
    ``geometry``: refgs.fast.render's per-Gaussian precision; "float64" is checked with the
    ties of GEOMETRY64_BANDS (no per-Gaussian bands), "input" with FLOAT32_BANDS."""
    g32 = g64.astype(np.float32)
    g64r = g32.astype(np.float64)                         # the same numbers in float64
    ref = refgs.render(g64r, cam, cfg)
    o64 = fast.render(g64r, cam, cfg)
    out = fast.render(g32, cam, cfg, geometry=geometry)
    assert out.image.dtype == np.float32
    ties = find_ties(o64, GEOMETRY64_BANDS if geometry == "float64" else FLOAT32_BANDS)
    fwd, bwd = ties["forward"], ties["backward"]
    assert fwd.mean() <= F32_MAX_TIE_FRACTION, ties["counts"]
    err = np.max(np.abs(out.image - ref.image), axis=-1)
    assert np.max(np.where(fwd, 0, err)) <= F32_ATOL, (np.max(np.where(fwd, 0, err)), ties["counts"])
    assert np.max(np.where(fwd, 0, np.abs(out.alpha - ref.alpha))) <= F32_ATOL
    zmax = max(float(np.max(np.abs(ref.depths[ref.visible]), initial=0)), 1.0)
    assert np.max(np.where(fwd, 0, np.abs(out.depth - ref.depth))) <= F32_ATOL * zmax
    H, W = ref.alpha.shape
    cot = random_cotangents(np.random.default_rng(seed), H, W)
    cot = {k: None if v is None else np.where(bwd[..., None] if v.ndim == 3 else bwd, 0, v)
           for k, v in cot.items()}
    gr = refgs.render_backward(ref, **cot)
    gf = fast.render_backward(out, **cot)
    rows = ~ties["kink_gaussians"]
    for k in GRAD_FIELDS:
        assert getattr(gf, k).dtype == np.float32, k
        err = grad_rel_l2(gf, gr, k, rows)
        assert err <= F32_GRAD_REL_L2, (k, err, ties["counts"])
    return {"tie_pixels": int(fwd.sum()), "flips": int(np.sum(fwd & (err > F32_ATOL))),
            "counts": ties["counts"]}


@settings(max_examples=max_examples(10))
@given(scene=scenes(n=(1, 8), width=(16, 48), height=(12, 40), sigma_px=(1.5, 4.0)))
def test_f32_random_scenes(scene):
    check_f32(scene.gaussians, scene.camera, scene.config, scene.seed % 1000)
    check_f32(scene.gaussians, scene.camera, scene.config, scene.seed % 1000, geometry="float64")


@pytest.mark.parametrize("geometry", ["float64", "input"])
@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_f32_benchmark_like_scene(profile, geometry):
    """A small benchmark scene (many overlaps, saturated pixels): float32 within tolerance
    outside near-ties, which are few."""
    g, cam = benchmark_scene(3000, 128, 96, seed=1)
    info = check_f32(g, cam, RenderConfig(profile=profile), geometry=geometry)
    assert info["tie_pixels"] <= 0.05 * 128 * 96


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_f32_geometry_is_decided_in_float64(profile):
    """geometry="float64" (float32 compositing of float64 geometry): every per-Gaussian decision -- visibility,
    radii, tile rectangles, depth order, so the (full) tile lists -- is the float64 render's, and
    the per-Gaussian outputs are the float64 ones rounded to float32.  (Which entries of the full
    lists are live depends on the compositing values: each live entry must be the float64 full
    list's entry at its recorded position.)"""
    g, cam = benchmark_scene(3000, 128, 96, seed=1)
    g64 = g.astype(np.float32).astype(np.float64)
    cfg = RenderConfig(profile=profile)
    o64 = fast.render(g64, cam, cfg)
    o32 = fast.render(g64.astype(np.float32), cam, cfg, geometry="float64")
    np.testing.assert_array_equal(o32.visible, o64.visible)
    np.testing.assert_array_equal(o32.radii, o64.radii)
    np.testing.assert_array_equal(o32.cache["tile_rect"], o64.cache["tile_rect"])
    full = fast.render(g64, cam, cfg, screen=False).cache["lists"]
    live = o32.cache["lists"]
    assert live["full_size"] == full["gauss"].size
    for t in range(full["offsets"].size - 1):
        f = full["gauss"][full["offsets"][t]:full["offsets"][t + 1]]
        a, b = live["offsets"][t], live["offsets"][t + 1]
        np.testing.assert_array_equal(live["gauss"][a:b], f[live["pos"][a:b]])
    for k in ("means2d", "conics", "depths", "colors", "opacities"):
        assert getattr(o32, k).dtype == np.float32
        np.testing.assert_array_equal(getattr(o32, k), getattr(o64, k).astype(np.float32), err_msg=k)
    grads = fast.render_backward(o32, np.ones(o32.image.shape, np.float32))
    assert all(getattr(grads, k).dtype == np.float32 for k in GRAD_FIELDS)
    with pytest.raises(ValueError, match="geometry"):
        fast.render(g64.astype(np.float32), cam, cfg, geometry="float16")


def test_gather_carries_a_float64_mean_as_value_plus_residual():
    """refgs.fast.tiles.gather: a float32 table of float64 means holds D(m) and D(m - D(m))
    (their float64 sum is m to ~2^-48 relative); a mean already in the table's dtype has residual
    exactly 0, so x + residual = x and those renders are unchanged bit for bit."""
    from refgs.fast import tiles as tl
    rng = np.random.default_rng(5)
    m64 = rng.uniform(-600, 1200, (64, 2))
    gauss = np.arange(64, dtype=np.int64)
    other = [np.zeros((64, 3), np.float32), np.zeros(64, np.float32), np.zeros((64, 3), np.float32),
             np.zeros(64, np.float32)]
    for means, dt in ((m64, np.float32), (m64.astype(np.float32), np.float32), (m64, np.float64)):
        tab = np.full((64, tl.N_TAB), np.nan, dt)
        tl.gather(gauss, 0, 64, means, other[0].astype(dt), other[1].astype(dt),
                  other[2].astype(dt), other[3].astype(dt), tab)
        np.testing.assert_array_equal(tab[:, :2], means.astype(dt))
        if means.dtype == dt:
            assert np.all(tab[:, 10:12] == 0)
        else:
            err = np.abs(tab[:, :2].astype(np.float64) + tab[:, 10:12] - means)
            assert np.all(err <= 2.0 ** -46 * np.abs(means)), err.max()


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_f32_compositing_of_f64_geometry_is_accurate_at_every_pixel(profile):
    """geometry="float64" keeps float64's 2D mean through the residual (docs/fast.md, Mixed
    precision): on a scene with needles and opaque Gaussians every pixel is within 2e-6 of the
    float64 render -- no near-tie pixel excluded -- and the unmasked gradients within 1e-5
    relative L2 (before the residual, 6 of these pixels were off by up to 8e-4 through alpha at
    1/255: a float32 mean alone is 3e-5 px off at 500 px)."""
    g, cam = benchmark_scene(20000, 504, 378, seed=3)
    g = g.astype(np.float32).astype(np.float64)
    g.log_scales[:200, 0] -= 4.0                 # needles
    g.opacity_logits[200:400] = 6.0              # nearly opaque
    cfg = RenderConfig(profile=profile)
    v = np.random.default_rng(1).normal(size=(378, 504, 3))
    o64 = fast.render(g, cam, cfg)
    o32 = fast.render(g.astype(np.float32), cam, cfg, geometry="float64")
    assert np.abs(o32.image.astype(np.float64) - o64.image).max() <= 2e-6
    g64 = fast.render_backward(o64, v)
    g32 = fast.render_backward(o32, v.astype(np.float32))
    for k in ("means", "log_scales", "quats", "opacity_logits", "sh", "means2d"):
        ref = getattr(g64, k)
        rel = np.linalg.norm(getattr(g32, k) - ref) / np.linalg.norm(ref)
        assert rel <= 1e-5, (k, rel)


# ---------------------------------------------------------------------------------------------
# determinism, API, packaging
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_deterministic_across_runs_and_thread_counts(dtype):
    g, cam = benchmark_scene(2000, 100, 70, seed=4)
    g = g.astype(dtype)
    v = np.random.default_rng(1).normal(size=(70, 100, 3))
    results = []
    threads = [numba.get_num_threads(), numba.get_num_threads(), 1]
    saved = numba.get_num_threads()
    try:
        for nt in threads:
            numba.set_num_threads(nt)
            out = fast.render(g, cam)
            results.append((out, fast.render_backward(out, v)))
    finally:
        numba.set_num_threads(saved)
    (o0, g0) = results[0]
    for o, gr in results[1:]:
        for k in PIXEL_FIELDS + ("n_contrib",):
            assert np.array_equal(getattr(o, k), getattr(o0, k)), k
        for k in GRAD_FIELDS:
            assert np.array_equal(getattr(gr, k), getattr(g0, k)), k


def test_parallel_pieces_give_the_sequential_result():
    """The depth sort, the tile lists and the per-Gaussian reduction split their work over the
    threads (refgs.fast.render: depth_order, build_tile_lists, parallel_bands); each must equal
    its one-thread form exactly, ties in depth included."""
    from refgs.fast import kernels as rk
    from refgs.fast import tiles as tl
    from refgs.fast.render import build_tile_lists, depth_order, parallel_bands

    rng = np.random.default_rng(3)
    n = 50000
    depths = rng.random(n)
    depths[::5] = 0.25                                  # many exact ties, broken by index
    idx = np.flatnonzero(rng.random(n) < 0.8)
    rect = np.zeros((n, 4), np.int64)
    rect[:, 0] = rng.integers(0, 7, n)
    rect[:, 1] = rect[:, 0] + rng.integers(0, 3, n)
    rect[:, 2] = rng.integers(0, 5, n)
    rect[:, 3] = rect[:, 2] + rng.integers(0, 4, n)
    np.minimum(rect[:, 1], 8, out=rect[:, 1])
    np.minimum(rect[:, 3], 6, out=rect[:, 3])
    expected_order = idx[np.argsort(depths[idx], kind="stable")]
    r = rect[expected_order]
    rect_off = np.concatenate([[0], np.cumsum((r[:, 1] - r[:, 0]) * (r[:, 3] - r[:, 2]))])
    live = rng.random(int(rect_off[-1])) < 0.7           # a live subset, as tile_alive gives
    full_g, full_off, full_pos = tl.build_tile_lists(expected_order, rect, 8 * 6, 8, rect_off,
                                                     np.ones(live.size, np.bool_))
    gauss1, offsets1, pos1 = tl.build_tile_lists(expected_order, rect, 8 * 6, 8, rect_off, live)
    # the live lists are the full lists filtered, each entry keeping its full-list position
    for t in range(8 * 6):
        fl = full_g[full_off[t]:full_off[t + 1]]
        assert np.array_equal(full_pos[full_off[t]:full_off[t + 1]], np.arange(fl.size))
        p = pos1[offsets1[t]:offsets1[t + 1]]
        assert np.all(np.diff(p) > 0) and np.array_equal(fl[p], gauss1[offsets1[t]:offsets1[t + 1]])
    assert gauss1.size == int(live.sum())
    contrib = rng.normal(size=(gauss1.size, rk.N_GRAD_COLUMNS))
    ref = np.zeros((n, rk.N_GRAD_COLUMNS))
    rk.reduce_by_gaussian(0, n, gauss1, contrib, ref)
    saved = numba.get_num_threads()
    try:
        for nt in sorted({1, saved, min(2, numba.config.NUMBA_NUM_THREADS)}):
            numba.set_num_threads(nt)
            assert np.array_equal(depth_order(idx, depths), expected_order), nt
            gauss, offsets, pos = build_tile_lists(expected_order, rect, 8, 6, rect_off, live)
            assert np.array_equal(gauss, gauss1) and np.array_equal(offsets, offsets1), nt
            assert np.array_equal(pos, pos1), nt
            out = np.zeros_like(ref)
            parallel_bands(rk.reduce_by_gaussian, n, gauss1, contrib, out)
            assert np.array_equal(out, ref), nt
    finally:
        numba.set_num_threads(saved)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_depth_order_is_the_stable_argsort(dtype):
    """refgs.fast.render.depth_order (a radix sort of the depths' bits) gives numpy's stable
    argsort: negative, zero (both signs), tiny, huge and tied depths; non-finite ones fall back."""
    from refgs.fast.render import depth_order
    rng = np.random.default_rng(11)
    n = 20000
    d = rng.normal(0, 3, n) * 10.0 ** rng.integers(-30, 30, n)
    d[::7] = 1.5
    d[::11] = 0.0
    d[::13] = -0.0
    d[::17] = -2.25
    d = d.astype(dtype)
    idx = np.flatnonzero(rng.random(n) < 0.9)
    expected = idx[np.argsort(d[idx], kind="stable")]
    assert np.array_equal(depth_order(idx, d), expected)
    d[idx[5]] = np.inf
    assert np.array_equal(depth_order(idx, d), idx[np.argsort(d[idx], kind="stable")])


def test_validation_errors():
    cam = Camera.look_at((0, 0, -4.0), (0, 0, 0), fx=25, width=20, height=17)
    g = Gaussians(np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 4)), np.zeros(1), np.zeros((1, 1, 3)))
    with pytest.raises(ValueError, match="quats"):
        fast.render(g, cam)
    g = g.replace(quats=np.array([[1.0, 0, 0, 0]]))
    ref = refgs.render(g, cam)
    with pytest.raises(ValueError, match="refgs.fast.render"):
        fast.render_backward(ref, np.zeros(ref.image.shape))
    out = fast.render(g, cam)
    with pytest.raises(ValueError, match="v_image"):
        fast.render_backward(out, np.zeros((3, 3, 3)))


def test_backend_objects():
    assert {b.dtype for b in (fast.fast_float32, fast.fast_float64)} == {"float32", "float64"}
    for b, profile, dtype in ((fast.fast_float32, "inria", "float32"),
                              (fast.fast_float64, "inria", "float64"),
                              (fast.fast_gsplat_float32, "gsplat", "float32"),
                              (fast.fast_gsplat_float64, "gsplat", "float64")):
        assert (b.profile, b.dtype, b.max_sh_degree, b.has_backward) == (profile, dtype, 3, True)
        assert b.name and b.version
    rng = np.random.default_rng(0)
    cam = make_camera(rng, 24, 20)
    g = place_gaussians(rng, cam, 4).astype(np.float32).astype(np.float64)
    cfg = RenderConfig(profile="gsplat", opacity_scale=np.ones(4))
    out = fast.fast_gsplat_float32.render(g, cam, cfg)
    assert out.image.dtype == np.float32
    grads = fast.fast_gsplat_float32.render_backward(out, np.ones(out.image.shape),
                                                     v_alpha=np.ones(out.alpha.shape))
    assert grads.means.dtype == np.float32 and grads.means.shape == (4, 3)
    with pytest.raises(ValueError, match="profile"):
        fast.fast_float32.render(g, cam, RenderConfig(profile="gsplat"))
    # the mixed precision backend renders exactly refgs.fast.render(..., geometry="float64")
    b = fast.fast_float32_geom64
    assert (b.profile, b.dtype, b.geometry) == ("inria", "float32", "float64") and "geom64" in b.name
    mixed = b.render(g, cam, RenderConfig())
    direct = fast.render(g.astype(np.float32), cam, RenderConfig(), geometry="float64")
    assert mixed.image.dtype == np.float32 and np.array_equal(mixed.image, direct.image)
    with pytest.raises(ValueError, match="geometry"):
        fast.FastBackend("inria", "float32", geometry="float16")
    protocol = pytest.importorskip("oracle.protocol")
    info = protocol.load_backend("refgs.fast:fast_float32")
    assert info.has_backward and info.dtype == "float32" and info.profile == "inria"


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_import_refgs_does_not_import_numba():
    r = _run("import sys, refgs; import refgs.render; print('numba' in sys.modules)")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False"


def test_clear_error_without_numba():
    r = _run("import sys; sys.modules['numba'] = None\n"
             "try:\n    import refgs.fast\nexcept ImportError as e:\n    print('IMPORTERROR', e)\n")
    assert r.returncode == 0, r.stderr
    assert "IMPORTERROR" in r.stdout and "pip install" in r.stdout and "refgs[numba]" in r.stdout
