"""The ablation variants of the method (FM-10, FM-11, FM-01 iso_fixed).

Same tiny synthetic scene as tests/test_method_training.py.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from refgs.methods.flat_minima import (OPACITY_SIGMA, ROTATION_SIGMA, SCALE_SIGMA, axis_angle_quats,
                                       quat_multiply)
from refgs.methods.flat_minima_method import FlatMinimaConfig, FlatMinimaMethod

from test_method_training import SMALL, make_trainer


def _request(perturb, t=30, iters=40, **kw):
    method = FlatMinimaMethod(FlatMinimaConfig(reinit_interval=10, reinit_window=4, perturb=perturb, **kw))
    tr = make_trainer(method, iters=iters)
    req = method.before_render(tr, t, np.random.default_rng(7))
    return tr, method, req


@pytest.mark.parametrize("perturb,changed", [("position", {"means"}), ("rotation", {"quats"}),
                                             ("scale", {"log_scales"}), ("opacity", {"opacity_logits"}),
                                             ("position+scale", {"means", "log_scales"})])
def test_fm10_only_the_chosen_fields_move_on_masked_rows(perturb, changed):
    tr, method, req = _request(perturb, p=0.5)
    theta, hat = tr.gaussians(), req.gaussians
    mask = method.last_mask
    assert 0 < mask.sum() < len(mask)
    for f in theta.FIELDS:
        a, b = getattr(theta, f), getattr(hat, f)
        if f in changed:
            assert not np.array_equal(a[mask], b[mask]), f
            assert np.array_equal(a[~mask], b[~mask]), f
        else:
            assert np.array_equal(a, b), f


def test_fm10_magnitudes_follow_gamma_alpha_and_the_named_sigmas():
    """Rotation angles, log-scale and logit offsets have std alpha gamma sigma (chi-square
    bounds on ~900 draws: a false alarm below 1e-6 per field)."""
    n_rep = 30
    for perturb, field, sigma, dof in (("rotation", "quats", ROTATION_SIGMA, 3),
                                       ("scale", "log_scales", SCALE_SIGMA, 3),
                                       ("opacity", "opacity_logits", OPACITY_SIGMA, 1)):
        samples = []
        for seed in range(n_rep):
            method = FlatMinimaMethod(FlatMinimaConfig(perturb=perturb, p=1.0, reinit=False))
            tr = make_trainer(method, iters=40)
            req = method.before_render(tr, 20, np.random.default_rng(seed))   # alpha = 1/2
            a, b = getattr(tr.gaussians(), field), getattr(req.gaussians, field)
            if perturb == "rotation":
                # q' = q * q(omega): the relative rotation's vector part is sin(|w|/2) w/|w|
                q = a / np.linalg.norm(a, axis=1, keepdims=True)
                conj = q * [1, -1, -1, -1]
                rel = quat_multiply(conj, b)
                half = np.arcsin(np.clip(np.linalg.norm(rel[:, 1:], axis=1), 0, 1))
                omega = rel[:, 1:] / np.maximum(np.sin(half), 1e-300)[:, None] * (2 * half)[:, None]
                samples.append(omega)
            else:
                samples.append((b - a).reshape(len(a), -1))
        x = np.concatenate(samples).ravel() / (0.5 * 2.0 * sigma)
        k = x.size
        chi2 = float(np.sum(x * x))
        # chi-square with k dof: mean k, sd sqrt(2k); 5 sd ~ a false alarm below 1e-6
        assert abs(chi2 - k) < 5 * np.sqrt(2 * k), (perturb, chi2, k)


def test_axis_angle_quats():
    w = np.array([[0.0, 0.0, 0.0], [np.pi, 0, 0], [0, 0, 1e-14]])
    q = axis_angle_quats(w)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0)
    np.testing.assert_allclose(q[0], [1, 0, 0, 0])
    np.testing.assert_allclose(q[1], [0, 1, 0, 0], atol=1e-15)


def test_fm11_mixed_gradient_exactly(monkeypatch):
    """FM-11: p = 1 (every Gaussian perturbed); the update gradient equals 0.5 (grads at
    theta_hat) + 0.5 (grads of a clean render of theta) for the same view and settings; the
    densification statistics take the perturbed render's screen-space gradient."""
    method = FlatMinimaMethod(FlatMinimaConfig(mixed_loss=True, reinit=False))
    tr = make_trainer(method, iters=40)
    for _ in range(15):
        tr.step()
    seen = {}
    real = tr.loss_and_grads

    def record(g, view, rcfg, t):
        res = real(g, view, rcfg, t)
        g = type(g)(**{k: getattr(g, k).copy() for k in g.FIELDS})     # Adam updates in place
        seen.setdefault("calls", []).append((g, view, rcfg, res[1]))
        return res

    stats_in = {}
    real_acc = tr.stats.accumulate
    monkeypatch.setattr(tr.stats, "accumulate",
                        lambda m2d, *a: (stats_in.setdefault("m2d", m2d.copy()), real_acc(m2d, *a))[1])

    monkeypatch.setattr(tr, "loss_and_grads", record)
    theta = tr.gaussians()
    theta = type(theta)(**{k: v.copy() for k, v in tr.params.items()})
    out = {}
    orig = method.after_backward
    monkeypatch.setattr(method, "after_backward",
                        lambda trainer, t, request, grads: out.setdefault("g", orig(trainer, t, request, grads)))
    tr.step()
    (g_hat, v1, c1, grads_hat), (g_clean, v2, c2, grads_clean) = seen["calls"]
    assert v1 is v2 and c1 is c2
    for f in theta.FIELDS:
        assert np.array_equal(getattr(g_clean, f), getattr(theta, f)), f
    assert not np.array_equal(g_hat.means, theta.means)
    assert method.last_mask.all()
    for k, v in out["g"].items():
        np.testing.assert_array_equal(v, 0.5 * grads_hat.params()[k] + 0.5 * grads_clean.params()[k])
    np.testing.assert_array_equal(stats_in["m2d"], grads_hat.means2d)
    assert not np.array_equal(grads_hat.means2d, grads_clean.means2d)


def test_fm01_iso_fixed_sigma_is_half_the_densification_threshold():
    method = FlatMinimaMethod(FlatMinimaConfig(noise="iso_fixed", p=1.0, schedule=False, clamp="none",
                                               reinit=False))
    tr = make_trainer(method, iters=40)
    expected = 0.5 * tr.cfg.densify.percent_dense * tr.extent
    assert method.fixed_sigma == pytest.approx(expected)
    req = method.before_render(tr, 10, np.random.default_rng(0))
    d = req.gaussians.means - tr.params["means"]
    # delta = gamma * sigma * R z: its norm^2 / (gamma sigma)^2 is chi-square(3) per Gaussian
    x = np.sum(d * d, axis=1) / (2.0 * expected) ** 2
    assert abs(x.mean() - 3) < 5 * np.sqrt(6 / len(x))
    explicit = FlatMinimaMethod(FlatMinimaConfig(noise="iso_fixed", noise_fixed_sigma=0.01))
    make_trainer(explicit, iters=40)
    assert explicit.fixed_sigma == 0.01


def test_ablation_flags_are_recorded_in_config(tmp_path):
    from refgs.cli import main

    from test_cli import tiny_args, write_tiny_scene
    scene = write_tiny_scene(tmp_path / "scene")
    out = tmp_path / "run"
    assert main(tiny_args(scene, out, 4, "--method", "fm", "--fm-perturb", "rotation", "--fm-mixed-loss",
                          "--fm-noise", "iso_fixed", "--fm-no-reinit")) == 0
    params = json.loads((out / "config.json").read_text())["settings"]["method_params"]
    assert params["perturb"] == "rotation" and params["mixed_loss"] is True
    assert params["noise"] == "iso_fixed" and params["reinit"] is False
    with pytest.raises(ValueError, match="--fm-perturb"):
        FlatMinimaConfig(perturb="colour")
    assert SMALL.perturb == "position" and not SMALL.mixed_loss
