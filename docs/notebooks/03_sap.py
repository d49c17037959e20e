# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 3. What Scale-Adaptive Perturbation does
#
# The paper's flat-minima method trains on **perturbed** Gaussians: at every iteration a random
# subset of positions is displaced before rendering, and the gradient taken there updates the
# unperturbed parameters (docs/spec/method.md, FM-01..FM-05). The displacement is
#
# $$x_i' = x_i + \alpha(t)\,\delta_i,\qquad \delta_i \sim \mathcal N(0,\ \gamma^2 \Sigma_i),\qquad \Sigma_i = R_i S_i S_i^\top R_i^\top,$$
#
# applied with probability $p$ per Gaussian, then clamped so that it "does not exceed the
# Gaussian's scale". It is *scale-adaptive*: a big, elongated Gaussian is shaken a lot along its
# long axis and hardly across it; a small one barely moves. The paper's values: $\gamma = 2$,
# $p = 0.3$, $\alpha(t) = t/T$. Everything below calls `refgs.methods` (refgs/methods/flat_minima.py).

# %%
import matplotlib.pyplot as plt
import numpy as np
from scipy.special import erfc

import refgs
from refgs.methods import (CLAMP_MODES, GAMMA, P_PERTURB, clamp_displacement, clipped_fraction,
                           magnitude_schedule, perturb_probability, sap_offsets)

# helpers beside this notebook (docs/notebooks/_helpers.py)
from _helpers import add_ellipse, clamp_bound

print(f"gamma = {GAMMA}, p = {P_PERTURB}, clamp readings {CLAMP_MODES}")

# %% [markdown]
# ## The offsets follow each Gaussian's own covariance
#
# Three Gaussians lying in the $xy$ plane, of different sizes and orientations. For each we draw
# many offsets with `sap_offsets` (here with $p = 1$, $\alpha = 1$ and no clamp, to see the raw
# distribution) and scatter the perturbed positions. Solid: the Gaussian's 1-sigma ellipse;
# dashed: the $\gamma$-sigma ellipse, where $\delta$'s own 1-sigma ellipse lies.

# %%
def gaussians_in_plane(centres, scales, angles_deg, copies=1):
    """Gaussians rotated about z by the given angles, each repeated ``copies`` times."""
    half = np.radians(np.asarray(angles_deg, float)) / 2
    quats = np.stack([np.cos(half), 0 * half, 0 * half, np.sin(half)], -1)
    n = len(centres)
    g = refgs.Gaussians(means=np.asarray(centres, float), log_scales=np.log(np.asarray(scales, float)),
                        quats=quats, opacity_logits=np.zeros(n), sh=np.zeros((n, 1, 3)))
    return g.subset(np.repeat(np.arange(n), copies))


centres = [[-1.2, 0.0, 0.0], [0.0, 0.0, 0.0], [1.1, 0.0, 0.0]]
scales = [[0.30, 0.08, 0.05], [0.12, 0.12, 0.05], [0.20, 0.05, 0.05]]
angles = [30.0, 0.0, -60.0]
M = 2000
cloud = gaussians_in_plane(centres, scales, angles, copies=M)
offsets, mask = sap_offsets(cloud, gamma=GAMMA, p=1.0, alpha=1.0, clamp=False,
                            rng=np.random.default_rng(0))
Sigma = refgs.covariance_3d(cloud.quats, cloud.log_scales)["cov3d"]

fig, ax = plt.subplots(figsize=(9, 3.8))
for k in range(3):
    rows = slice(k * M, (k + 1) * M)
    pts = cloud.means[rows] + offsets[rows]
    ax.scatter(pts[:400, 0], pts[:400, 1], s=3, alpha=0.5)
    add_ellipse(ax, centres[k][:2], Sigma[k * M][:2, :2], 1.0, color="k")
    add_ellipse(ax, centres[k][:2], Sigma[k * M][:2, :2], GAMMA, color="k", ls="--")
ax.set_aspect("equal")
ax.set_title("400 perturbed positions per Gaussian (p = 1, alpha = 1, no clamp)", fontsize=9)
plt.show()

# the sample covariance of delta is gamma^2 Sigma (FM-01)
for k in range(3):
    rows = slice(k * M, (k + 1) * M)
    emp = np.cov(offsets[rows].T)
    err = np.linalg.norm(emp - GAMMA**2 * Sigma[k * M]) / np.linalg.norm(GAMMA**2 * Sigma[k * M])
    print(f"Gaussian {k}: |cov(delta) - gamma^2 Sigma| / |gamma^2 Sigma| = {err:.3f}")
    assert err < 0.15, err

# %% [markdown]
# ## Only some Gaussians are perturbed
#
# Each Gaussian is perturbed with probability $p$ (FM-02); the others get an offset of exactly 0.
# (The paper calls it $p_{\max}$ but ramps only the magnitude; `perturb_probability(..., ramp=True)`
# is DropGaussian's ramped form, kept for the ablations.)

# %%
offsets, mask = sap_offsets(cloud, rng=np.random.default_rng(1))        # paper defaults
print(f"perturbed fraction {mask.mean():.3f} (p = {P_PERTURB})")
assert abs(mask.mean() - P_PERTURB) < 0.02
assert np.all(offsets[~mask] == 0) and np.all(np.any(offsets[mask] != 0, axis=1))

# %% [markdown]
# ## The schedule $\alpha(t) = t/T$
#
# The displacement grows linearly over training (FM-03): no perturbation at the start, when the
# Gaussians are still far from any minimum, the full $\gamma$-sized one at the end. Below, the
# schedule and the perturbed positions of one elongated Gaussian at three moments of a run of
# $T = 10\,000$ iterations, with the default clamp.

# %%
T = 10_000
t = np.arange(0, T + 1, 100)
one = gaussians_in_plane([[0.0, 0.0, 0.0]], [[0.30, 0.08, 0.05]], [30.0], copies=600)

fig, axes = plt.subplots(1, 4, figsize=(13, 3.0))
axes[0].plot(t, [magnitude_schedule(k, T) for k in t], label="alpha(t) = t / T")
axes[0].plot(t, [perturb_probability(k, T) for k in t], label="p (constant)")
axes[0].plot(t, [perturb_probability(k, T, ramp=True) for k in t], ls=":",
             label="p ramped (DropGaussian form)")
axes[0].set_xlabel("iteration t")
axes[0].legend(fontsize=7)
for ax, tt in zip(axes[1:], [1_000, 5_000, 10_000]):
    a = magnitude_schedule(tt, T)
    off, m = sap_offsets(one, p=1.0, alpha=a, rng=np.random.default_rng(2))
    ax.scatter(off[:, 0], off[:, 1], s=3, alpha=0.5)
    add_ellipse(ax, (0, 0), refgs.covariance_3d(one.quats[:1], one.log_scales[:1])["cov3d"][0][:2, :2],
                1.0, color="k")
    ax.set_xlim(-0.4, 0.4)
    ax.set_ylim(-0.3, 0.3)
    ax.set_aspect("equal")
    ax.set_title(f"t = {tt}: alpha = {a:.1f}", fontsize=9)
plt.tight_layout()
plt.show()
assert [magnitude_schedule(k, T) for k in (0, T // 2, T)] == [0.0, 0.5, 1.0]

# %% [markdown]
# ## The clamp: four readings of one sentence
#
# "Perturbed positions are clamped so that the displacement does not exceed the corresponding
# Gaussian's scale." In the Gaussian's principal frame, $l = R^\top \alpha\delta$, that can mean
# (FM-04, `CLAMP_MODES`):
#
# * `axis` (default): clip every component, $|l_k| \le s_k$ — moves samples onto the box, bending
#   their direction;
# * `box`: shrink the whole vector until it fits the same box — keeps the direction;
# * `ellipsoid`: shrink it into the 1-sigma ellipsoid $\lVert l/s \rVert \le 1$;
# * `norm`: shrink it to length $\lVert s \rVert_2$.
#
# Grey: 300 unclamped draws; colour: the same draws clamped (same seed), with a thin line from
# each of the first 40 draws to where the clamp put it; black: the allowed region (projected on the
# first two principal axes; the third axis also counts in 3D).

# %%
s = np.array([0.30, 0.12, 0.06])
one = gaussians_in_plane([[0.0, 0.0, 0.0]], [s], [30.0], copies=1500)
R = refgs.quat_to_rotmat(refgs.normalize_quats(one.quats)[0])[0]
raw, _ = sap_offsets(one, p=1.0, alpha=1.0, clamp="none", rng=np.random.default_rng(3))
l_raw = raw @ R                                                      # rows: R^T delta

fig, axes = plt.subplots(1, 4, figsize=(13, 3.3), sharey=True)
bounds_ok = {}
for ax, mode, colour in zip(axes, ["axis", "box", "ellipsoid", "norm"],
                            ["tab:blue", "tab:orange", "tab:green", "tab:red"]):
    off, _ = sap_offsets(one, p=1.0, alpha=1.0, clamp=mode, rng=np.random.default_rng(3))
    l = off @ R
    ax.scatter(l_raw[:300, 0], l_raw[:300, 1], s=3, color="0.75")
    ax.plot(np.stack([l_raw[:40, 0], l[:40, 0]]), np.stack([l_raw[:40, 1], l[:40, 1]]), color=colour,
            lw=0.6, alpha=0.7)
    ax.scatter(l[:300, 0], l[:300, 1], s=3, color=colour)
    clamp_bound(ax, mode, s)
    ax.set_xlim(-1.0, 1.0)
    ax.set_ylim(-0.45, 0.45)
    ax.set_aspect("equal")
    ax.set_title(f"clamp = {mode!r}", fontsize=9)
    ax.set_xlabel("principal axis 1")
    tol = 1 + 1e-12
    bounds_ok[mode] = bool({"axis": np.all(np.abs(l) <= s * tol), "box": np.all(np.abs(l) <= s * tol),
                            "ellipsoid": np.all(np.linalg.norm(l / s, axis=1) <= tol),
                            "norm": np.all(np.linalg.norm(l, axis=1) <= np.linalg.norm(s) * tol)}[mode])
    # the clamp applied to the unclamped draws reproduces what sap_offsets returned
    assert np.allclose(clamp_displacement(l_raw, np.broadcast_to(s, l_raw.shape), mode), l, atol=1e-12)
axes[0].set_ylabel("principal axis 2")
plt.tight_layout()
plt.show()
print("every clamped sample inside its region:", bounds_ok)
assert all(bounds_ok.values())

# the three shrinking readings keep the direction of the draw; 'axis' does not
for mode in ["box", "ellipsoid", "norm", "axis"]:
    off, _ = sap_offsets(one, p=1.0, alpha=1.0, clamp=mode, rng=np.random.default_rng(3))
    cos = np.sum(off * raw, 1) / (np.linalg.norm(off, axis=1) * np.linalg.norm(raw, axis=1))
    print(f"{mode:>9}: smallest cosine(clamped, unclamped) = {cos.min():.4f}")
    assert (cos.min() > 1 - 1e-12) == (mode != "axis")

# %% [markdown]
# ## How often does the clamp bind?
#
# The clamp acts in units of $s$, so how often it changes a draw depends only on
# $\alpha\gamma$, not on the Gaussian: for `axis`, a component is clipped with probability
# $\operatorname{erfc}\!\left(1/(\sqrt2\,\alpha\gamma)\right)$. With $\gamma = 2$ the clamp starts to
# matter from $\alpha \approx 0.2$ — one fifth into training — and at the end it changes most
# draws: the paper's "clamp" is not a rare safety net but shapes the perturbation
# (`clipped_fraction`, Monte-Carlo; per axis for `axis`, per Gaussian for the others).

# %%
alphas = np.linspace(0.0, 1.0, 21)
frac = {mode: np.array([clipped_fraction(a, mode, n=20_000) for a in alphas])
        for mode in ["axis", "box", "ellipsoid", "norm"]}
with np.errstate(divide="ignore"):
    exact_axis = erfc(1.0 / (np.sqrt(2) * alphas * GAMMA))

fig, ax = plt.subplots(figsize=(6, 3.6))
for mode, f in frac.items():
    ax.plot(alphas, f, marker=".", label=mode)
ax.plot(alphas, exact_axis, "k:", label="axis, erfc formula")
ax.set_xlabel("alpha(t)")
ax.set_ylabel("fraction changed by the clamp")
ax.legend(fontsize=8)
plt.show()
print("alpha:   ", alphas[::5])
for mode, f in frac.items():
    print(f"{mode:>9}:", f[::5].round(3))

# %%
assert np.max(np.abs(frac["axis"] - exact_axis)) < 0.01
assert all(f[0] == 0.0 for f in frac.values())
