"""The paper's method and DropGaussian inside the trainer (FM-05..FM-08, DG-02, TRN-08).

A tiny synthetic scene (views rendered by refgs from random Gaussians) trains a few dozen
iterations; reinit interval and window are scaled down (interval 10, window 4) so every rule is
exercised in seconds.  The rules are the same at the paper's 1000 / 100.
"""
from __future__ import annotations

import numpy as np
import pytest

import refgs
from refgs.errors import ConfigError
from refgs.methods import METHOD_NAMES, make_method, method_params
from refgs.methods.dropgaussian_method import DropGaussianMethod
from refgs.methods.flat_minima_method import FlatMinimaConfig, FlatMinimaMethod
from refgs.backends import get_backend
from refgs.train.densify import DensifyConfig
from refgs.train.hooks import Method
from refgs.train.trainer import TrainConfig, Trainer, View

W, H = 32, 24
N_TRUE = 30


def scene(seed=0):
    rng = np.random.default_rng(seed)
    means = rng.uniform(-1, 1, (N_TRUE, 3)) * [1.0, 0.8, 0.3]
    sh = np.zeros((N_TRUE, 16, 3))
    sh[:, 0] = (rng.uniform(0.1, 0.9, (N_TRUE, 3)) - 0.5) / refgs.constants.SH_C0
    g = refgs.Gaussians(means, np.full((N_TRUE, 3), np.log(0.2)), np.tile([1.0, 0, 0, 0], (N_TRUE, 1)),
                        np.full(N_TRUE, 1.5), sh)
    views = []
    for k, a in enumerate(np.radians([-30, 0, 30, 15])):
        cam = refgs.Camera.look_at([4 * np.sin(a), 0.2, -4 * np.cos(a)], [0, 0, 0], fx=30.0, width=W, height=H)
        views.append(View(f"v{k}", cam, np.clip(refgs.render(g, cam).image, 0, 1)))
    init = {"means": means + rng.normal(0, 0.05, means.shape), "log_scales": np.full((N_TRUE, 3), np.log(0.15)),
            "quats": np.tile([1.0, 0, 0, 0], (N_TRUE, 1)), "opacity_logits": np.full(N_TRUE, -2.2),
            "sh": sh * 0.8}
    return views[:3], views[3:], init


def make_config(method_name: str, iters=40, densify=None, seed=0, params=None) -> TrainConfig:
    dcfg = densify or DensifyConfig(start=3, interval=5, until=iters, grad_threshold=0.0002,
                                    opacity_reset_interval=10_000)
    # float64: the method's identities (FM-05's replayed Adam step, bit-exact resumes) are checked
    # in the reference's exact arithmetic, not the float32 training default
    return TrainConfig(scene="synthetic", views=3, iters=iters, seed=seed, densify=dcfg, lpips=False,
                       method=method_name, method_params=params or {}, dtype="float64")


def make_trainer(method: Method, iters=40, densify=None, seed=0):
    train_views, test_views, init = scene()
    cfg = make_config(method.name, iters, densify, seed)
    return Trainer(cfg, train_views, test_views, init, extent=4.0,
                   backend=get_backend("reference", dtype=cfg.dtype), method=method)


SMALL = FlatMinimaConfig(reinit_interval=10, reinit_window=4)
#: the one-line error of an unknown --method (the same from make_method and TrainConfig.validate)
UNKNOWN_METHOD = r"^--method: expected one of \['3dgs', 'dropgaussian', 'fm'\], got 'sam'$"


def test_fm05_gradients_at_theta_hat():
    """FM-05: the update uses render_backward evaluated at theta_hat (positions + delta), and after
    the step theta's positions contain no delta: x_{t+1} = x_t - Adam(grad at theta_hat)."""
    method = FlatMinimaMethod(SMALL)
    tr = make_trainer(method, iters=40)
    for _ in range(25):                       # alpha(t) > 0 and several perturbed Gaussians
        tr.step()
    before = {k: v.copy() for k, v in tr.params.items()}
    captured = {}
    backend = tr.backend

    class Spy:
        name = "spy"

        def render(self, g, cam, cfg):
            # copies: the trainer's Gaussians share memory with the parameters Adam updates
            captured["g"] = refgs.Gaussians(*(getattr(g, f).copy() for f in g.FIELDS))
            captured["cam"], captured["cfg"] = cam, cfg
            return backend.render(g, cam, cfg)

        def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
            captured["v_image"] = np.array(v_image, copy=True)
            captured["grads"] = backend.render_backward(out, v_image, v_alpha, v_depth)
            return captured["grads"]

    tr.backend = Spy()
    adam_before = {k: (tr.adam.m[k].copy(), tr.adam.v[k].copy()) for k in tr.params}
    tr.step()
    g_hat = captured["g"]
    offsets = g_hat.means - before["means"]
    mask = method.last_mask
    assert mask.any() and np.all(offsets[~mask] == 0) and np.any(offsets[mask] != 0)
    # the rendered parameters are theta except for the positions
    for k in ("log_scales", "quats", "opacity_logits", "sh"):
        assert np.array_equal(getattr(g_hat, k), before[k])
    # recompute the gradient at theta_hat independently (a fresh render and backward at the
    # captured theta_hat and cotangent): every field equals what the trainer used
    out = refgs.render(g_hat, captured["cam"], captured["cfg"])
    g_ind = refgs.render_backward(out, captured["v_image"])
    for k in g_ind.params():
        assert np.array_equal(getattr(g_ind, k), getattr(captured["grads"], k)), k
    # replay Adam on theta with those gradients: every field moved along Adam(grad at theta_hat)
    # (one learning rate per field, and per SH slice: DC and the rest)
    b1, b2 = tr.adam.betas
    for k, sl in (("means", ...), ("log_scales", ...), ("quats", ...), ("opacity_logits", ...),
                  ("sh", (slice(None), slice(0, 1)))):
        g = getattr(g_ind, k)[sl]
        m = b1 * adam_before[k][0][sl] + (1 - b1) * g
        v = b2 * adam_before[k][1][sl] + (1 - b2) * g * g
        step = (tr.params[k] - before[k])[sl]  # the applied update
        expected_dir = -m / (np.sqrt(v) + tr.adam.eps)
        live = np.abs(expected_dir) > 1e-9
        if not live.any():      # quats of isotropic Gaussians (just reinitialised): no gradient
            assert k == "quats" and np.all(np.abs(step) < 1e-12), k
            continue
        ratio = step[live] / expected_dir[live]
        assert np.allclose(ratio, ratio.flat[0], rtol=1e-5), f"{k}: update is not Adam(grad at theta_hat)"
    # theta holds no delta: undoing the step returns exactly the old positions
    assert not np.allclose(tr.params["means"][mask], g_hat.means[mask])


def test_fm06_reinit_iterations_and_window():
    """FM-06..FM-08: reinit at t = 10 k <= T - 10 only; scale, rotation, SH rest reset and frozen
    for exactly W = 4 iterations (no change at all), DC colour, positions, N untouched; opacity
    reset at each interval."""
    iters = 40
    method = FlatMinimaMethod(SMALL)
    tr = make_trainer(method, iters=iters, densify=DensifyConfig(start=1000, interval=100, until=iters,
                                                                  opacity_reset_interval=10_000))
    from refgs.data.init import knn_log_scales
    history = []
    for _ in range(iters):
        before = {k: v.copy() for k, v in tr.params.items()}
        tr.step()
        history.append((tr.t, before, {k: v.copy() for k, v in tr.params.items()}))
    reinit_ts = [t for t in range(1, iters + 1) if t % 10 == 0 and t <= iters - 10]
    assert reinit_ts == [10, 20, 30]
    for t, before, after in history:
        if t in reinit_ts:
            expected = knn_log_scales(after["means"])
            expected = expected if expected.ndim == 2 else np.repeat(expected[:, None], 3, 1)
            assert np.allclose(after["log_scales"], expected)
            assert np.all(after["quats"] == [1, 0, 0, 0]) and np.all(after["sh"][:, 1:] == 0)
            assert np.all(refgs.render.__globals__["expit"](after["opacity_logits"]) <= 0.01 + 1e-12)
            assert len(after["means"]) == len(before["means"])
        elif any(t0 < t <= t0 + 4 for t0 in reinit_ts):
            for k in ("log_scales", "quats"):
                assert np.array_equal(after[k], before[k]), (t, k)
            assert np.array_equal(after["sh"][:, 1:], before["sh"][:, 1:]), t
            assert not np.array_equal(after["sh"][:, 0], before["sh"][:, 0]), t      # DC trains
            assert not np.array_equal(after["means"], before["means"]), t
        elif t > 1 and t < iters:
            assert not np.array_equal(after["log_scales"], before["log_scales"]), t
    # no reinit in the last interval
    last = [h for h in history if h[0] == 40][0]
    assert not np.all(last[2]["quats"] == [1, 0, 0, 0])


def test_fm08_children_of_frozen_gaussians_stay_frozen():
    """FM-08: Gaussians made by densification inside a window inherit the frozen state."""
    method = FlatMinimaMethod(FlatMinimaConfig(reinit_interval=10, reinit_window=6))
    dcfg = DensifyConfig(start=3, interval=12, until=40, grad_threshold=1e-9, opacity_reset_interval=10_000)
    tr = make_trainer(method, iters=40, densify=dcfg)
    for _ in range(12):                      # reinit at 10, densify at 12 (inside the window)
        tr.step()
    assert tr.n > N_TRUE
    assert np.all(method.frozen_until == 16)
    rows = method.frozen_rows(tr, 13)
    assert rows is not None and rows["log_scales"].shape == (tr.n,) and rows["log_scales"].all()
    before = tr.params["log_scales"].copy()
    tr.step()
    assert np.array_equal(tr.params["log_scales"], before)


def test_dg02_dropgaussian_scales_opacity_in_training_only():
    """DG-01/DG-02: the training render gets keep/(1-r) opacity factors; test renders do not."""
    method = DropGaussianMethod()
    tr = make_trainer(method, iters=20)
    seen = []
    backend = tr.backend

    class Spy:
        name = "spy"

        def render(self, g, cam, cfg):
            seen.append(cfg.opacity_scale)
            return backend.render(g, cam, cfg)

        def render_backward(self, *a):
            return backend.render_backward(*a)

    tr.backend = Spy()
    for _ in range(10):
        tr.step()
    r = 0.2 * 10 / 20
    last = seen[-1]
    assert last is not None and set(np.unique(last)) <= {0.0, 1.0 / (1.0 - r)}
    seen.clear()
    tr.test_psnr()
    assert all(s is None for s in seen)


def test_dg02_method_names_and_plugin():
    """DG-02: --method {3dgs, fm, dropgaussian} and the plug-in --method dropgaussian --fm."""
    assert METHOD_NAMES == ("3dgs", "dropgaussian", "fm")
    assert type(make_method("3dgs")) is Method
    assert isinstance(make_method("fm"), FlatMinimaMethod)
    assert isinstance(make_method("dropgaussian"), DropGaussianMethod)
    plug = make_method("dropgaussian", {"fm": True})
    assert isinstance(plug, FlatMinimaMethod) and plug.drop is not None
    params = plug.params_dict()
    assert params["gamma"] == 2.0 and params["p"] == 0.3 and params["r_max"] == 0.2
    on_3dgs = make_method("3dgs", {"fm": True, "gamma": 1.0})
    assert type(on_3dgs) is FlatMinimaMethod and on_3dgs.drop is None and on_3dgs.config.gamma == 1.0
    assert make_method("dropgaussian", {"r_max": 0.3}).r_max == 0.3
    with pytest.raises(ConfigError, match=UNKNOWN_METHOD):
        make_method("sam")
    with pytest.raises(ConfigError, match="method parameters: unknown"):
        make_method("fm", {"gama": 1.0})


def test_dg02_recorded_parameters_rebuild_the_method():
    """DG-02: method_params records every parameter (given over defaults); make_method of the
    record builds the same method; options that do not apply are refused naming the option."""
    rec = method_params("fm", {"gamma": 1.5, "reinit_window": 7})
    assert list(rec) == list(FlatMinimaConfig.__dataclass_fields__)
    assert rec["gamma"] == 1.5 and rec["reinit_window"] == 7 and rec["p"] == 0.3 and "fm" not in rec
    assert make_method("fm", rec).config == FlatMinimaConfig(gamma=1.5, reinit_window=7)
    plug = method_params("dropgaussian", {"r_max": 0.1}, fm=True)
    assert plug["r_max"] == 0.1 and plug["fm"] is True and list(plug)[-2:] == ["r_max", "fm"]
    rebuilt = make_method("dropgaussian", plug)
    assert rebuilt.name == "dropgaussian+fm" and rebuilt.drop.r_max == 0.1
    assert method_params("3dgs", {}) == {} and method_params("dropgaussian", {}) == {"r_max": 0.2}
    assert method_params("fm", {"gamma": None}) == method_params("fm", {})
    with pytest.raises(ConfigError, match=r"^--fm-\*: flat-minima options need --method fm or --fm$"):
        method_params("dropgaussian", {"gamma": 1.0})
    with pytest.raises(ConfigError, match=r"^--drop-r-max: only with --method dropgaussian$"):
        method_params("fm", {"r_max": 0.1})
    with pytest.raises(ConfigError, match="--method"):
        method_params("sam", {})


def test_trn08_method_names_are_checked_by_the_caller():
    """TRN-08: training does not import the methods; TrainConfig.validate checks --method against
    the names its caller gives, and a trainer without a method object runs only plain 3DGS."""
    with pytest.raises(ConfigError, match=UNKNOWN_METHOD):
        make_config("sam").validate(METHOD_NAMES)
    assert make_config("sam").validate() is not None          # no names given: not checked
    train_views, test_views, init = scene()
    with pytest.raises(ConfigError, match="--method fm"):
        Trainer(make_config("fm"), train_views, test_views, init, 4.0, get_backend("reference"))
    plain = Trainer(make_config("3dgs"), train_views, test_views, init, 4.0, get_backend("reference"))
    assert type(plain.method) is Method
    import ast
    from pathlib import Path
    for path in sorted((Path(refgs.__file__).parent / "train").glob("*.py")):
        module = path.stem
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                assert "methods" not in (node.module or "").split("."), (module, node.module)
            elif isinstance(node, ast.Import):
                assert not any("methods" in a.name.split(".") for a in node.names), module


def test_fm_training_is_deterministic():
    """Same seed, same parameters after training with perturbations and reinit."""
    a = make_trainer(FlatMinimaMethod(SMALL), iters=15, seed=4)
    b = make_trainer(FlatMinimaMethod(SMALL), iters=15, seed=4)
    for _ in range(15):
        a.step()
        b.step()
    for k in a.params:
        assert np.array_equal(a.params[k], b.params[k]), k


def test_fm07_densified_gaussians_are_reinitialised():
    """FM-06/FM-07: at an iteration where densification and reinit coincide (t = 10 here), the
    order is densify -> reinit -> opacity reset: every current Gaussian, the children made a moment
    before included, gets the SfM-style state computed from the current positions."""
    from refgs.data.init import knn_log_scales
    method = FlatMinimaMethod(SMALL)
    dcfg = DensifyConfig(start=5, interval=5, until=40, grad_threshold=1e-9, opacity_reset_interval=10_000)
    tr = make_trainer(method, iters=40, densify=dcfg)
    for _ in range(9):
        tr.step()
    n_before = tr.n
    tr.step()                                   # t = 10: densify, then reinit
    assert tr.t == 10 and tr.n > n_before       # children were made at this very iteration
    p = tr.params
    expected = knn_log_scales(p["means"])
    expected = expected if expected.ndim == 2 else np.repeat(expected[:, None], 3, 1)
    assert np.allclose(p["log_scales"], expected)
    assert np.all(p["quats"] == [1, 0, 0, 0]) and np.all(p["sh"][:, 1:] == 0)
    assert np.all(refgs.render.__globals__["expit"](p["opacity_logits"]) <= 0.01 + 1e-12)
    assert method.frozen_until.shape == (tr.n,) and np.all(method.frozen_until == 10 + SMALL.reinit_window)
    for name in ("log_scales", "quats"):
        assert not tr.adam.m[name].any() and not tr.adam.v[name].any()


@pytest.mark.parametrize("standard_interval", [10, 10_000])
def test_fm06_standard_opacity_reset_at_a_reinit_iteration_happens_once(standard_interval, monkeypatch):
    """FM-06/FM-07: at a reinit iteration the opacity is reset exactly once -- by the standard
    schedule when it is due at that iteration (interval 10 = the reinit interval here), else by
    the reinit -- and ends <= 0.01 with zeroed Adam moments; SH-rest moments are zeroed too."""
    import refgs.methods.flat_minima_method as mt
    import refgs.train.strategy as ts          # the paper's strategy resets opacity (TRN-06, TRN-14)
    calls = []

    def counting(name, real):
        def f(params, adam):
            calls.append((name, tr.t + 1))
            return real(params, adam)
        return f

    monkeypatch.setattr(mt, "reset_opacity", counting("reinit", mt.reset_opacity))
    monkeypatch.setattr(ts, "reset_opacity", counting("standard", ts.reset_opacity))
    method = FlatMinimaMethod(SMALL)
    tr = make_trainer(method, iters=40, densify=DensifyConfig(start=1000, interval=100, until=40,
                                                              opacity_reset_interval=standard_interval))
    for _ in range(10):
        tr.step()
    at_10 = [c for c in calls if c[1] == 10]
    assert at_10 == [("standard" if standard_interval == 10 else "reinit", 10)], calls
    p = tr.params
    assert np.all(refgs.render.__globals__["expit"](p["opacity_logits"]) <= 0.01 + 1e-12)
    assert not tr.adam.m["opacity_logits"].any() and not tr.adam.v["opacity_logits"].any()
    assert not tr.adam.m["sh"][:, 1:].any() and not tr.adam.v["sh"][:, 1:].any()


def test_trn09_fm_state_resumes_bit_exactly():
    """TRN-09: a checkpoint inside a frozen window (reinit at 10, window 4, densification at 10)
    restores the method's state (``method/frozen_until``) and the optimiser's, and the resumed
    run ends with the parameters of the uninterrupted one."""
    dcfg = DensifyConfig(start=5, interval=5, until=40, grad_threshold=1e-9, opacity_reset_interval=10_000)
    full = make_trainer(FlatMinimaMethod(SMALL), iters=30, densify=dcfg, seed=2)
    for _ in range(11):
        full.step()
    arrays = {k: np.array(v) for k, v in full.state_arrays().items()}
    meta = full.state_meta()
    assert "method/frozen_until" in arrays and np.all(arrays["method/frozen_until"] == 14)
    for _ in range(5):
        full.step()
    train_views, test_views, _ = scene()
    params = {k[6:]: v for k, v in arrays.items() if k.startswith("param/")}
    method = FlatMinimaMethod(SMALL)
    resumed = Trainer(make_config("fm", 30, dcfg, 2), train_views, test_views, params, 4.0,
                      get_backend("reference"), method)
    resumed.load_state(arrays, meta)
    assert np.array_equal(method.frozen_until, arrays["method/frozen_until"])
    for _ in range(5):
        resumed.step()
    for k in full.params:
        assert np.array_equal(full.params[k], resumed.params[k]), k
        assert np.array_equal(full.adam.m[k], resumed.adam.m[k]), k
