"""Adaptive density control (docs/spec/training.md TRN-04..TRN-06): statistics in NDC units,
clone, split, prune, opacity reset, and Adam moments that stay on their Gaussians."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.special import expit, logit

import refgs
from refgs.train.adam import Adam
from refgs.train.densify import (DENSIFY_PRESETS, DensifyConfig, DensifyStats, densify_and_prune,
                                 densify_preset, reset_opacity)

EXTENT = 2.0
CFG = DensifyConfig(grad_threshold=0.0005)  # percent_dense 0.01 -> clone if max scale <= 0.02


def make_params(log_scale_rows, opacities, rng):
    n = len(opacities)
    q = rng.standard_normal((n, 4))
    return {"means": rng.standard_normal((n, 3)),
            "log_scales": np.log(np.asarray(log_scale_rows, float)),
            "quats": q, "opacity_logits": logit(np.asarray(opacities, float)),
            "sh": rng.standard_normal((n, 4, 3))}


def stats_with(grads):
    s = DensifyStats(len(grads))
    s.grad_accum = np.asarray(grads, float) * 2
    s.denom = np.full(len(grads), 2.0)
    return s


def stepped_adam(params, rng):
    adam = Adam(params)
    adam.step(params, {k: rng.standard_normal(v.shape) for k, v in params.items()},
              {k: 0.0 for k in params})  # lr 0: parameters unchanged, moments set
    return adam


def test_stats_accumulate_ndc_units_and_visible_only():
    s = DensifyStats(3)
    g_pix = np.array([[1e-4, 2e-4], [3e-4, -1e-4], [5.0, 5.0]])
    radii = np.array([[3, 3], [1, 1], [0, 0]])
    s.accumulate(g_pix, radii, width=504, height=378)
    s.accumulate(g_pix, np.array([[2, 2], [0, 0], [0, 0]]), width=504, height=378)
    ndc = np.linalg.norm(g_pix * [252.0, 189.0], axis=1)   # 0.5 W, 0.5 H
    np.testing.assert_allclose(s.grad_accum, [2 * ndc[0], ndc[1], 0.0], rtol=1e-15)
    assert s.denom.tolist() == [2, 1, 0]
    assert s.max_radii.tolist() == [3, 1, 0]
    np.testing.assert_allclose(s.mean_grad(), [ndc[0], ndc[1], 0.0], rtol=1e-15)


def test_clone_split_prune_and_adam_state():
    rng = np.random.default_rng(0)
    #            0: clone     1: split     2: quiet small  3: quiet big  4: prune (low opacity)
    scales = [[0.01] * 3, [0.3, 0.1, 0.05], [0.01] * 3, [0.3] * 3, [0.01] * 3]
    opac = [0.5, 0.6, 0.7, 0.8, 0.004]
    p = make_params(scales, opac, rng)
    old = {k: v.copy() for k, v in p.items()}
    adam = stepped_adam(p, rng)
    m_old = {k: v.copy() for k, v in adam.m.items()}
    v_old = {k: v.copy() for k, v in adam.v.items()}
    stats = stats_with([1e-3, 1e-3, 1e-4, 1e-4, 1e-4])
    split_rng = np.random.default_rng(7)
    remap = densify_and_prune(p, stats, adam, CFG, EXTENT, False, split_rng)
    # rows: originals 0, 2, 3 (1 split away, 4 pruned), clone of 0, then the 2 split children
    assert remap.parent.tolist() == [0, 2, 3, 0, 1, 1]
    assert remap.source.tolist() == [0, 2, 3, -1, -1, -1]
    assert (remap.n_cloned, remap.n_split, remap.n_pruned) == (1, 1, 1)
    for k in p:
        assert len(p[k]) == 6 and adam.m[k].shape == p[k].shape and adam.v[k].shape == p[k].shape
        assert np.array_equal(p[k][:3], old[k][[0, 2, 3]])
        assert np.array_equal(adam.m[k][:3], m_old[k][[0, 2, 3]])
        assert np.array_equal(adam.v[k][:3], v_old[k][[0, 2, 3]])
        assert np.all(adam.m[k][3:] == 0) and np.all(adam.v[k][3:] == 0)
        if k not in ("means", "log_scales"):
            assert np.array_equal(p[k][3], old[k][0]) and np.array_equal(p[k][4:], old[k][[1, 1]])
    assert np.array_equal(p["means"][3], old["means"][0])          # a clone is a copy
    assert np.array_equal(p["log_scales"][3], old["log_scales"][0])
    # split children: scale / 1.6, x = R n + x0 with n ~ N(0, diag(s^2)) from the run's stream
    s1 = np.array(scales[1])
    np.testing.assert_allclose(np.exp(p["log_scales"][4:]), [s1 / 1.6] * 2, rtol=1e-15)
    n = np.random.default_rng(7).standard_normal((2, 3)) * s1
    R = refgs.quat_to_rotmat(refgs.normalize_quats(old["quats"][[1]])[0])[0]
    np.testing.assert_allclose(p["means"][4:], n @ R.T + old["means"][1], rtol=1e-14, atol=1e-15)
    assert stats.grad_accum.shape == (6,) and not stats.denom.any()


def test_clones_are_not_split_in_the_same_pass():
    rng = np.random.default_rng(1)
    p = make_params([[0.01] * 3], [0.5], rng)
    remap = densify_and_prune(p, stats_with([1.0]), Adam(p), CFG, EXTENT, False, rng)
    assert len(p["means"]) == 2 and remap.n_split == 0


def test_split_samples_follow_the_covariance():
    """Offsets of many children have covariance R S^2 R^T (COV-01)."""
    rng = np.random.default_rng(2)
    n = 4000
    q = np.tile([0.9, 0.3, -0.2, 0.25], (n, 1))
    s = np.array([0.5, 0.2, 0.05])
    p = {"means": np.zeros((n, 3)), "log_scales": np.tile(np.log(s), (n, 1)), "quats": q,
         "opacity_logits": np.zeros(n), "sh": np.zeros((n, 1, 3))}
    densify_and_prune(p, stats_with(np.ones(n)), Adam(p), CFG, EXTENT, False, rng)
    assert len(p["means"]) == 2 * n
    R = refgs.quat_to_rotmat(refgs.normalize_quats(q[:1])[0])[0]
    expected = R @ np.diag(s ** 2) @ R.T
    np.testing.assert_allclose(np.cov(p["means"].T), expected, atol=4 * 0.25 / np.sqrt(n))


def test_size_pruning():
    rng = np.random.default_rng(3)
    p = make_params([[0.01] * 3, [0.25] * 3, [0.01] * 3], [0.5, 0.5, 0.5], rng)  # 0.25 > 0.1*2
    stats = stats_with([0.0, 0.0, 0.0])
    stats.max_radii = np.array([5.0, 5.0, 30.0])
    q = {k: v.copy() for k, v in p.items()}
    densify_and_prune(p, stats, Adam(p), CFG, EXTENT, False, rng)
    assert len(p["means"]) == 3                      # size pruning inactive
    upstream = DensifyConfig(size_prune=True)
    densify_and_prune(p, stats_with([0.0] * 3), Adam(p), upstream, EXTENT, True, rng)
    assert len(p["means"]) == 2                      # world size only (3DGS@82bc469 quirk)
    stats = stats_with([0.0] * 3)
    stats.max_radii = np.array([5.0, 5.0, 30.0])
    acc = DensifyConfig(size_prune=True, screen_size_rule="accumulated")
    densify_and_prune(q, stats, Adam(q), acc, EXTENT, True, rng)
    assert np.array_equal(q["means"], make_params([[0.01] * 3] * 3, [0.5] * 3,
                                                  np.random.default_rng(3))["means"][[0]])


def test_opacity_reset():
    rng = np.random.default_rng(4)
    p = make_params([[0.01] * 3] * 3, [0.9, 0.01, 0.002], rng)
    adam = stepped_adam(p, rng)
    steps = dict(adam.steps)
    m_scale = adam.m["log_scales"].copy()
    reset_opacity(p, adam)
    np.testing.assert_allclose(expit(p["opacity_logits"]), [0.01, 0.01, 0.002], rtol=1e-12)
    assert np.all(adam.m["opacity_logits"] == 0) and np.all(adam.v["opacity_logits"] == 0)
    assert adam.steps == steps and np.array_equal(adam.m["log_scales"], m_scale)


def test_presets():
    d, o = DENSIFY_PRESETS["dropgaussian"], DENSIFY_PRESETS["original"]
    assert (d.grad_threshold, d.until, d.size_prune, d.start, d.interval) == (0.0005, None, False, 500, 100)
    assert (o.grad_threshold, o.until, o.size_prune) == (0.0002, 15000, True)
    assert d.resolved_until(10_000) == 10_000 and o.resolved_until(10_000) == 10_000
    assert o.resolved_until(30_000) == 15_000
    assert densify_preset("original", interval=7).interval == 7
    with pytest.raises(ValueError, match="--densify-preset"):
        densify_preset("fast")


def _tiny_trainer(iters=12, **kw):
    from refgs.backends import get_backend
    from refgs.train.trainer import TrainConfig, Trainer, View

    rng = np.random.default_rng(5)
    n = 30
    g = refgs.Gaussians(rng.uniform(-1, 1, (n, 3)) * [1, 0.8, 0.2], np.full((n, 3), np.log(0.15)),
                        np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.5), rng.normal(0, 0.5, (n, 16, 3)))
    views = []
    for k, a in enumerate(np.radians([-20, 0, 20])):
        cam = refgs.Camera.look_at([4 * np.sin(a), 0.2, -4 * np.cos(a)], [0, 0, 0], fx=30,
                                   width=32, height=24)
        views.append(View(f"v{k}", cam, np.clip(refgs.render(g, cam).image, 0, 1)))
    init = g.replace(means=g.means + rng.normal(0, 0.05, (n, 3)), sh=g.sh * 0.5)
    cfg = TrainConfig.with_preset("dropgaussian", dict(start=2, interval=3, **kw), scene="-",
                                  views=3, iters=iters)
    return Trainer(cfg, views, views[:1], init.to_dict(), 1.0, get_backend("reference"))


def test_trainer_skips_adam_on_densify_iterations():
    """As 3DGS: the densification iteration replaces every tensor (no Adam step); the opacity
    reset iteration replaces only the opacity; no step at t = T."""
    tr = _tiny_trainer(iters=7, opacity_reset_interval=5)
    counts = []
    for _ in range(7):
        tr.step()
        counts.append(dict(tr.adam.steps))
    # t=3 and t=6 densify (t > 2, t % 3 == 0); t=5 resets opacity; t=7 = T: no step
    assert [c["means"] for c in counts] == [1, 2, 2, 3, 4, 4, 4]
    assert [c["opacity_logits"] for c in counts] == [1, 2, 2, 3, 3, 3, 3]


def test_trainer_reduces_loss():
    tr = _tiny_trainer(iters=40, until=0)
    losses = [tr.step()["loss"] for _ in range(40)]
    assert np.mean(losses[-6:]) < 0.8 * np.mean(losses[:6])


def test_method_hooks_reach_the_loop():
    """A Method sees every iteration (TRN-08): its opacity_scale reaches the renderer, its
    gradients are what Adam applies, its frozen rows stay put, on_densify sees the remap."""
    from refgs.train.hooks import Method, RenderRequest

    class Probe(Method):
        name = "probe"

        def __init__(self):
            self.remaps, self.steps = [], []

        def before_render(self, trainer, t, rng):
            scale = np.ones(trainer.n)
            scale[0] = 0.0                       # Gaussian 0 invisible: zero gradient
            return RenderRequest(trainer.gaussians(), opacity_scale=scale)

        def after_backward(self, trainer, t, request, grads):
            assert not np.any(grads.means[0]) and not np.any(grads.opacity_logits[0])
            return {k: -v for k, v in grads.params().items()}   # ascend instead of descend

        def frozen_rows(self, trainer, t):
            rows = np.zeros(trainer.n, bool)
            rows[1] = True
            return {k: rows for k in trainer.params}

        def on_densify(self, trainer, remap):
            self.remaps.append(remap)

        def after_step(self, trainer, t, rng):
            self.steps.append(t)

    tr = _tiny_trainer(iters=6, until=0)                 # no densification
    probe = Probe()
    tr.method = probe
    first = {k: v[1].copy() for k, v in tr.params.items()}
    losses = [tr.step()["loss"] for _ in range(5)]
    assert probe.steps == [1, 2, 3, 4, 5] and probe.remaps == []
    for k, v in first.items():                                          # row 1 never moved
        assert np.array_equal(tr.params[k][1], v)
    assert losses[-1] > losses[0]                                       # gradient ascent
    tr = _tiny_trainer(iters=6)                          # densification at t = 3
    tr.method = probe = Probe()
    for _ in range(4):
        tr.step()
    assert len(probe.remaps) == 1 and len(probe.remaps[0].parent) == tr.n
