"""Adam and the learning-rate schedules (docs/spec/training.md TRN-02, TRN-03)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from refgs.train.adam import ADAM_EPS, Adam
from refgs.train.schedule import (FEATURE_LR, POSITION_LR_FINAL, POSITION_LR_INIT,
                                  learning_rates, position_lr, scene_extent, sh_degree_at, sh_lr)


def _params(rng, n=5, k=4):
    return {"means": rng.standard_normal((n, 3)), "sh": rng.standard_normal((n, k, 3)),
            "opacity_logits": rng.standard_normal(n)}


def test_adam_matches_torch():
    """Same trajectory as torch.optim.Adam(eps=1e-15) with 3DGS-style groups (f_dc, f_rest
    as separate torch groups; one (N, K, 3) array with a (1, K, 1) lr here), including a step
    where one group has no gradient (skipped, step count not advanced)."""
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(0)
    p = _params(rng)
    lrs = {"means": 0.01, "sh": sh_lr(4), "opacity_logits": 0.05}
    t_means = torch.tensor(p["means"], requires_grad=True)
    t_dc = torch.tensor(p["sh"][:, :1].copy(), requires_grad=True)
    t_rest = torch.tensor(p["sh"][:, 1:].copy(), requires_grad=True)
    t_op = torch.tensor(p["opacity_logits"], requires_grad=True)
    opt = torch.optim.Adam([{"params": [t_means], "lr": 0.01},
                            {"params": [t_dc], "lr": FEATURE_LR},
                            {"params": [t_rest], "lr": FEATURE_LR / 20},
                            {"params": [t_op], "lr": 0.05}], lr=0.0, eps=1e-15)
    adam = Adam(p)
    for step in range(12):
        g = {k: rng.standard_normal(v.shape) * 10.0 ** rng.integers(-3, 2) for k, v in p.items()}
        skip = {"opacity_logits"} if step in (4, 7) else set()
        adam.step(p, g, lrs, skip=skip)
        t_means.grad = torch.tensor(g["means"])
        t_dc.grad = torch.tensor(g["sh"][:, :1].copy())
        t_rest.grad = torch.tensor(g["sh"][:, 1:].copy())
        t_op.grad = None if skip else torch.tensor(g["opacity_logits"])
        opt.step()
    np.testing.assert_allclose(p["means"], t_means.detach().numpy(), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(p["sh"][:, :1], t_dc.detach().numpy(), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(p["sh"][:, 1:], t_rest.detach().numpy(), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(p["opacity_logits"], t_op.detach().numpy(), rtol=1e-13, atol=1e-15)
    assert adam.steps == {"means": 12, "sh": 12, "opacity_logits": 10}
    assert int(opt.state[t_op]["step"]) == 10


def test_adam_first_step_is_lr_times_sign():
    """Step 1: m/(1-b1) = g, sqrt(v/(1-b2)) = |g|, so the move is lr * g / (|g| + eps)."""
    p = {"x": np.array([1.0, 2.0, 3.0])}
    g = {"x": np.array([0.5, -2e-3, 0.0])}
    Adam(p).step(p, g, {"x": 0.1})
    np.testing.assert_allclose(p["x"], [1.0 - 0.1, 2.0 + 0.1 * 2e-3 / (2e-3 + ADAM_EPS), 3.0],
                               rtol=1e-15)


def test_adam_frozen_rows():
    rng = np.random.default_rng(1)
    p = _params(rng)
    q = {k: v.copy() for k, v in p.items()}
    a, b = Adam(p), Adam(q)
    g = {k: rng.standard_normal(v.shape) for k, v in p.items()}
    frozen = np.array([True, False, False, True, False])
    a.step(p, g, {k: 0.1 for k in p}, frozen_rows={"means": frozen})
    b.step(q, g, {k: 0.1 for k in q})
    assert np.array_equal(p["means"][frozen], _params(np.random.default_rng(1))["means"][frozen])
    assert np.array_equal(p["means"][~frozen], q["means"][~frozen])
    assert np.all(a.m["means"][frozen] == 0) and np.array_equal(a.m["means"][~frozen], b.m["means"][~frozen])
    assert np.array_equal(p["sh"], q["sh"])


def test_adam_remap_equals_stepping_the_kept_rows():
    """Adam acts row by row: remapping (prune + append) and stepping equals stepping the rows
    separately, with fresh rows starting from zero moments (TRN-05)."""
    rng = np.random.default_rng(2)
    p = _params(rng, n=6)
    adam = Adam(p)
    for _ in range(3):
        adam.step(p, {k: rng.standard_normal(v.shape) for k, v in p.items()}, {k: 0.01 for k in p})
    source = np.array([0, 2, 5, -1, 3, -1])
    m_before = {k: v.copy() for k, v in adam.m.items()}
    new = {k: np.concatenate([v[[0, 2, 5]], v[[1]], v[[3]], v[[4]]]) for k, v in p.items()}
    adam.remap(source)
    for k in p:
        assert np.array_equal(adam.m[k][[0, 1, 2, 4]], m_before[k][[0, 2, 5, 3]])
        assert np.all(adam.m[k][[3, 5]] == 0) and np.all(adam.v[k][[3, 5]] == 0)
    g = {k: rng.standard_normal(v.shape) for k, v in new.items()}
    # reference: the kept rows alone with their own moments, the fresh rows with a new Adam
    kept = {k: v[[0, 1, 2, 4]].copy() for k, v in new.items()}
    ref = Adam(kept)
    for k in kept:
        ref.m[k], ref.v[k] = adam.m[k][[0, 1, 2, 4]].copy(), adam.v[k][[0, 1, 2, 4]].copy()
        ref.steps[k] = adam.steps[k]
    adam.step(new, g, {k: 0.01 for k in new})
    ref.step(kept, {k: v[[0, 1, 2, 4]] for k, v in g.items()}, {k: 0.01 for k in kept})
    for k in new:
        assert np.array_equal(new[k][[0, 1, 2, 4]], kept[k])


def test_adam_reset_rows():
    """reset_rows zeroes the moments of the given rows only (bool rows, row indices, or a mask
    broadcasting against the parameter), keeps the step count, and the next step of those rows
    is the step of fresh moments at that count (FM-07/FM-08)."""
    rng = np.random.default_rng(4)
    p = _params(rng, n=6, k=4)
    adam = Adam(p)
    for _ in range(3):
        adam.step(p, {k: rng.standard_normal(v.shape) for k, v in p.items()}, {k: 0.01 for k in p})
    m0 = {k: v.copy() for k, v in adam.m.items()}
    v0 = {k: v.copy() for k, v in adam.v.items()}
    rows = np.array([True, False, True, False, False, False])
    adam.reset_rows("means", rows)
    adam.reset_rows("opacity_logits", np.array([1, 4]))
    sh_mask = np.zeros((6, 4, 1), bool)
    sh_mask[:, 1:, 0] = rows[:, None]               # SH coefficients k >= 1 of rows 0 and 2
    adam.reset_rows("sh", sh_mask)
    assert np.all(adam.m["means"][rows] == 0) and np.all(adam.v["means"][rows] == 0)
    assert np.array_equal(adam.m["means"][~rows], m0["means"][~rows])
    assert np.array_equal(adam.v["means"][~rows], v0["means"][~rows])
    keep = np.ones(6, bool)
    keep[[1, 4]] = False
    assert np.all(adam.m["opacity_logits"][~keep] == 0)
    assert np.array_equal(adam.m["opacity_logits"][keep], m0["opacity_logits"][keep])
    full = np.broadcast_to(sh_mask, p["sh"].shape)
    assert np.all(adam.m["sh"][full] == 0) and np.all(adam.v["sh"][full] == 0)
    assert np.array_equal(adam.m["sh"][~full], m0["sh"][~full])
    assert np.array_equal(adam.v["sh"][~full], v0["sh"][~full])
    assert adam.steps == {"means": 3, "sh": 3, "opacity_logits": 3}
    # the next step of a reset row: fresh moments, bias-corrected with step count 4
    g = {k: rng.standard_normal(v.shape) for k, v in p.items()}
    x0 = p["means"][rows].copy()
    adam.step(p, g, {k: 0.01 for k in p})
    b1, b2 = adam.betas
    m = (1 - b1) * g["means"][rows]
    v = (1 - b2) * g["means"][rows] ** 2
    expected = x0 - 0.01 / (1 - b1 ** 4) * m / (np.sqrt(v) / np.sqrt(1 - b2 ** 4) + ADAM_EPS)
    np.testing.assert_allclose(p["means"][rows], expected, rtol=1e-14, atol=0)
    # resetting every row is zero()
    other = Adam(p)
    other.load_state_arrays(adam.state_arrays())
    adam.reset_rows("sh", np.ones(6, bool))
    other.zero("sh")
    assert np.array_equal(adam.m["sh"], other.m["sh"]) and np.array_equal(adam.v["sh"], other.v["sh"])
    with pytest.raises(ValueError, match="reset_rows"):
        adam.reset_rows("sh", np.ones((6, 3, 1), bool))
    with pytest.raises(ValueError, match="reset_rows"):
        adam.reset_rows("means", np.array([0.5]))


def test_adam_float32_stays_float32():
    p = {"x": np.ones(4, np.float32)}
    adam = Adam(p)
    adam.step(p, {"x": np.ones(4, np.float32)}, {"x": 1e-3})
    assert p["x"].dtype == np.float32 and adam.m["x"].dtype == np.float32


def test_adam_state_round_trip():
    rng = np.random.default_rng(3)
    p = _params(rng)
    adam = Adam(p)
    adam.step(p, {k: rng.standard_normal(v.shape) for k, v in p.items()}, {k: 0.1 for k in p})
    other = Adam(p)
    other.load_state_arrays(adam.state_arrays())
    assert other.steps == adam.steps
    for k in p:
        assert np.array_equal(other.m[k], adam.m[k]) and np.array_equal(other.v[k], adam.v[k])


# --- schedules ----------------------------------------------------------------------------
def test_position_lr_log_linear():
    e, T = 2.5, 10_000
    assert position_lr(0, T, e) == pytest.approx(POSITION_LR_INIT * e, rel=1e-14)
    assert position_lr(T, T, e) == pytest.approx(POSITION_LR_FINAL * e, rel=1e-14)
    assert position_lr(3 * T, T, e) == pytest.approx(POSITION_LR_FINAL * e, rel=1e-14)
    # log-linear: the midpoint is the geometric mean; no delay multiplier at small t
    assert position_lr(T // 2, T, e) == pytest.approx(math.sqrt(1.6e-4 * 1.6e-6) * e, rel=1e-12)
    assert position_lr(1, T, e) == pytest.approx(1.6e-4 * e * 100 ** (-1 / T), rel=1e-12)
    assert position_lr(5, T, 0.0) == 0.0


def test_horizon_is_iters():
    """The schedule's horizon is T = --iters: at t = T the final lr is reached for any T."""
    for T in (300, 2000):
        assert position_lr(T, T, 1.0) == pytest.approx(1.6e-6, rel=1e-13)
        assert position_lr(T // 2, T, 1.0) == pytest.approx(1.6e-5, rel=1e-12)


def test_learning_rates_groups():
    lrs = learning_rates(1, 100, 1.0, 16)
    assert lrs["opacity_logits"] == 0.05 and lrs["log_scales"] == 0.005 and lrs["quats"] == 0.001
    assert lrs["sh"].shape == (1, 16, 1)
    assert lrs["sh"][0, 0, 0] == 0.0025 and np.all(lrs["sh"][0, 1:, 0] == 0.0025 / 20)


def test_scene_extent():
    c = np.array([[0.0, 0, 0], [2, 0, 0], [1, 3, 0]])
    mean = c.mean(0)
    assert scene_extent(c) == pytest.approx(1.1 * np.linalg.norm(c - mean, axis=1).max(), rel=1e-15)
    assert scene_extent(c[:1]) == 0.0


def test_sh_degree_schedule():
    assert [sh_degree_at(t) for t in (1, 999, 1000, 1999, 2000, 3000, 9000)] == [0, 0, 1, 1, 2, 3, 3]
    assert sh_degree_at(5000, max_degree=1) == 1
