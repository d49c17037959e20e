"""The one backend registry (refgs.backends, docs/architecture.md): every name resolves to a
renderer with its capabilities, the trainer, ``refgs bench`` and the oracle resolve the same
names, and ``module:object`` plugs an outside renderer into all three with one spelling."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap
from types import SimpleNamespace

import numpy as np
import pytest

import refgs
from refgs.backends import (BACKENDS, BackendUnavailable, ReferenceBackend, available_backends,
                            get_backend)
from refgs.errors import ConfigError
from refgs.synthetic import benchmark_scene

HAS_NUMBA = importlib.util.find_spec("numba") is not None
needs_numba = pytest.mark.skipif(not HAS_NUMBA, reason="needs numba")


def test_one_registry():
    assert importlib.util.find_spec("refgs.train.backend") is None
    assert available_backends()[:2] == ["reference", "fast"]
    assert {"ref64", "ref32", "fast64", "fast32", "fast32g", "torch64", "torch32",
            "gsplat"} <= set(BACKENDS)


def test_reference_names_render_the_spec_bit_for_bit():
    g, cam = benchmark_scene(200, 40, 30, seed=1)
    want = refgs.render(g, cam, refgs.RenderConfig())
    for name in ("reference", "ref64"):
        be = get_backend(name, "inria", "float64")
        assert (be.profile, be.dtype, be.has_backward) == ("inria", "float64", True)
        assert not any(hasattr(be, h) for h in ("adam_update", "ssim_and_grad", "l1_ssim_loss"))
        out = be.render(g, cam, refgs.RenderConfig())
        assert np.array_equal(out.image, want.image)
    be32 = get_backend("ref32")
    assert be32.label == "refgs reference float32" and be32.dtype == "float32"
    out = be32.render(g, cam, refgs.RenderConfig())
    assert out.image.dtype == np.float32
    assert np.array_equal(out.image, refgs.render(g.astype(np.float32), cam).image)


def test_unknown_and_empty_names_are_one_line_errors():
    with pytest.raises(ConfigError) as e:
        get_backend("cuda")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("--backend: unknown backend 'cuda'")
    assert all(name in msg for name in BACKENDS) and "module:object" in msg
    with pytest.raises(ConfigError, match="--backends: expected a backend name"):
        get_backend("  ", flag="--backends")
    with pytest.raises(ConfigError, match="cannot import module 'no_such_module_xyz'"):
        get_backend("no_such_module_xyz:obj")
    with pytest.raises(ConfigError, match="has no attribute 'nope'"):
        get_backend("refgs.backends:nope")


def test_unsupported_combinations_are_one_line_errors():
    with pytest.raises(BackendUnavailable, match="^--backend ref32: renders dtype float32 only, "
                                                 "not float64$"):
        get_backend("ref32", "inria", "float64")
    with pytest.raises(BackendUnavailable, match="^--backends gsplat: renders profile gsplat only"):
        get_backend("gsplat", "inria", flag="--backends")
    with pytest.raises(BackendUnavailable, match="renders dtype float32 only"):
        get_backend("oracle.adapters.refgs_backend:refgs_float32", dtype="float64")


@needs_numba
def test_fast_names_carry_the_training_helpers():
    from refgs.fast.adam import adam_update
    from refgs.fast.ssim import l1_ssim_loss, ssim_and_grad

    for name, dtype in (("fast", "float64"), ("fast64", "float64"), ("fast32", "float32")):
        be = get_backend(name)
        assert be.dtype == dtype and be.profile == "inria" and be.label == f"refgs.fast {dtype}"
        assert be.adam_update is adam_update and be.ssim_and_grad is ssim_and_grad
        assert be.l1_ssim_loss is l1_ssim_loss
    g = get_backend("fast32g")
    assert (g.renderer.geometry, g.bands) == ("float64", "float32-compositing")
    assert get_backend("fast", "gsplat", "float32").renderer.profile == "gsplat"


def test_registry_import_keeps_the_core_numpy_only():
    code = ("import sys, refgs.backends, refgs.runs\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in "
            "('numba', 'torch', 'gsplat', 'oracle')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr


OUTSIDE = '''
import refgs
from refgs.backends import ReferenceBackend


class Outside:
    """An outside renderer: refgs at float64 under another name, counting its calls."""
    profile, dtype, name = "inria", "float64", "outside"

    def __init__(self):
        self.calls = 0
        self._inner = ReferenceBackend("inria", "float64")

    def render(self, gaussians, camera, config=None):
        self.calls += 1
        return self._inner.render(gaussians, camera, config)

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        return self._inner.render_backward(out, v_image, v_alpha, v_depth)


backend = Outside()
'''


def test_module_object_plugs_in_everywhere(tmp_path, monkeypatch):
    """One spelling for the trainer, the bench and the oracle."""
    from oracle.protocol import load_backend
    from refgs.analysis.bench import bench_backend
    from refgs.train.trainer import TrainConfig, Trainer, View
    from refgs.methods import make_method

    (tmp_path / "outside_renderer.py").write_text(textwrap.dedent(OUTSIDE))
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    spec = "outside_renderer:backend"
    info = load_backend(spec)                                  # the oracle
    assert (info.name, info.profile, info.dtype, info.has_backward) == ("outside", "inria",
                                                                        "float64", True)
    bb = bench_backend(spec, "inria")                          # the bench
    assert (bb.label, bb.dtype) == (spec, "float64")
    g, cam = benchmark_scene(60, 32, 24, seed=2)               # the trainer
    view = View("v", cam, np.clip(refgs.render(g, cam).image, 0, 1))
    cfg = TrainConfig(scene="-", views=1, iters=3, backend=spec, lpips=False, dtype="float64")
    params = g.replace(means=g.means + 0.01).to_dict()
    runs = {}
    for name in (spec, "reference"):
        tr = Trainer(cfg, [view], [view], params, 1.0, get_backend(name, cfg.profile, cfg.dtype),
                     make_method(cfg.method, cfg.method_params))
        for _ in range(3):
            tr.step()
        runs[name] = tr.params
    assert sys.modules["outside_renderer"].backend.calls == 3
    for k, v in runs["reference"].items():
        assert np.array_equal(runs[spec][k], v), k


def test_oracle_names_through_the_registry():
    from oracle.protocol import BackendError, load_backend

    for name, dtype in (("ref64", "float64"), ("ref32", "float32"), ("reference", "float64")):
        info = load_backend(name)
        assert info.dtype == dtype and set(info.stages) == {"covariance", "projection", "sh",
                                                            "composite"}
    with pytest.raises(BackendError, match="unknown backend 'cuda'"):
        load_backend("cuda")
    if importlib.util.find_spec("gsplat") is not None:
        info = load_backend("gsplat")                # an unavailable renderer is judged as n/a
        assert info.profile == "gsplat" and (info.unavailable_reason is None) == info.has_backward


def test_bench_lists_what_cannot_run(tmp_path):
    from refgs.analysis import bench

    args = SimpleNamespace(n=[40], size=["24x16"], backends=["ref64", "gsplat"], fern_run=None,
                           repeats=1, profile="inria", out=str(tmp_path), no_plots=True)
    doc = bench.run(args, progress=False)
    assert sorted(doc["results"][0]["backends"]) == ["ref64"]
    assert "gsplat" in doc["unavailable"] and "--backends" not in doc["unavailable"]["gsplat"]


def test_reference_backend_follows_its_input_without_a_profile_or_dtype():
    g, cam = benchmark_scene(50, 24, 16, seed=3)
    be = ReferenceBackend(None, None)
    out = be.render(g.astype(np.float32), cam, refgs.RenderConfig(profile="gsplat"))
    assert out.image.dtype == np.float32
    with pytest.raises(ValueError, match="RenderConfig.profile"):
        ReferenceBackend("inria", "float64").render(g, cam, refgs.RenderConfig(profile="gsplat"))
