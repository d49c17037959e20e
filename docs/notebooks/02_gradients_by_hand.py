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
# # 2. Gradients by hand, checked by finite differences
#
# refgs has no autodiff: `refgs.render_backward` is the chain rule written out stage by stage
# (derivations in `docs/derivations/`: covariance, projection, sh, compositing). A hand-written
# gradient is only as good as its check, so here we hold it against **central finite differences**
# in float64:
#
# $$\frac{\partial L}{\partial \theta_k} \approx \frac{L(\theta + h e_k) - L(\theta - h e_k)}{2h},$$
#
# Richardson-extrapolated, $(4 D(h/2) - D(h))/3$, so that the $O(h^2)$ error cancels. The loss is a
# fixed random linear functional of all three outputs,
# $L = \langle V_I, \text{image}\rangle + \langle V_\alpha, \text{alpha}\rangle + \langle V_D, \text{depth}\rangle$,
# so every path through the renderer is exercised (its gradient is what `render_backward(out,
# V_I, V_alpha, V_D)` returns).

# %%
import matplotlib.pyplot as plt
import numpy as np

import refgs
from refgs.constants import ALPHA_MIN

# helpers beside this notebook (docs/notebooks/_helpers.py)
from _helpers import FD_STEP, fd_gradient, relative_error, show_image, text_table

# %% [markdown]
# ## A scene away from the model's discontinuities
#
# The renderer is only piecewise smooth: a fragment is skipped when its alpha drops below
# $1/255$ (RAS-04), a colour channel is clamped at 0 (CNV-10), the radius is a `ceil` (PRF-04)
# deciding which tiles see a Gaussian (RAS-01). A finite difference that straddles one of those
# jumps measures the jump, not the derivative. So the scene is checked to sit away from all of
# them: every fragment's alpha at least 1 % away from $1/255$, every colour channel at least 0.05
# above 0, and every Gaussian's radius large enough that it covers all four tiles of the 32×24
# image whatever its `ceil` does. (The 0.99 alpha cap and the transmittance stop at $10^{-4}$
# cannot be reached by three Gaussians of opacity at most 0.7.)

# %%
W, H = 32, 24
cam = refgs.Camera.look_at(eye=[0.4, -0.3, -3.0], target=[0.0, 0.0, 0.0], fx=40.0, width=W, height=H)
config = refgs.RenderConfig(profile="inria", background=(0.1, 0.2, 0.3))


def random_scene(rng, n=3):
    """n anisotropic Gaussians near the origin, SH degree 1, opacities 0.35..0.7."""
    q = rng.normal(size=(n, 4))
    sh = rng.normal(0.0, 0.15, (n, 4, 3))
    sh[:, 0] = rng.uniform(0.2, 1.0, (n, 3))
    return refgs.Gaussians(means=rng.uniform(-0.3, 0.3, (n, 3)),
                           log_scales=np.log(rng.uniform(0.3, 0.9, (n, 3))),
                           quats=q, opacity_logits=rng.uniform(-0.6, 0.85, n), sh=sh)


def fragment_alphas(out):
    """alpha = o exp(power) of every (Gaussian, pixel) pair, (N, H, W), before the cap and skip."""
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)        # pixel centres (CNV-08)
    dx = jj[None] - out.means2d[:, 0, None, None]
    dy = ii[None] - out.means2d[:, 1, None, None]
    A, B, C = (out.conics[:, k, None, None] for k in range(3))
    return out.opacities[:, None, None] * np.exp(-0.5 * (A * dx * dx + C * dy * dy) - B * dx * dy)


def safe_for_fd(out):
    alpha_margin = np.min(np.abs(np.log(fragment_alphas(out) / ALPHA_MIN)))
    rgb = out.cache["sh"]["colors"]
    covers_all = np.all(out.radii >= 20) and np.all((out.means2d > 0) & (out.means2d < [W, H]))
    return alpha_margin > 0.01 and rgb.min() > 0.05 and covers_all, alpha_margin


rng = np.random.default_rng(7)
for attempt in range(100):
    g = random_scene(rng)
    out = refgs.render(g, cam, config)
    ok, margin = safe_for_fd(out)
    if ok:
        break
print(f"scene accepted after {attempt + 1} draw(s); closest fragment alpha is "
      f"{100 * (np.exp(margin) - 1):.1f} % away from 1/255; radii {out.radii[:, 0]}")
fig, ax = plt.subplots(1, 2, figsize=(7, 2.6))
show_image(ax[0], out.image, "image")
show_image(ax[1], out.alpha, "alpha", cmap="gray", vmin=0, vmax=1)
plt.show()

# %% [markdown]
# ## Every field against finite differences
#
# One backward pass gives all gradients; the finite differences need two renders per parameter
# per step size. The error measure is $\max_k |g_k - \hat g_k| / \max_k |\hat g_k|$ per field.

# %%
V_I = rng.normal(size=(H, W, 3))
V_a = rng.normal(size=(H, W))
V_D = rng.normal(size=(H, W))


def loss(gaussians):
    o = refgs.render(gaussians, cam, config)
    return float(np.sum(V_I * o.image) + np.sum(V_a * o.alpha) + np.sum(V_D * o.depth))


grads = refgs.render_backward(out, V_I, V_a, V_D)

rows, errors = [], {}
for field in refgs.Gaussians.FIELDS:
    fd = fd_gradient(lambda x: loss(g.replace(**{field: x})), getattr(g, field))
    errors[field] = relative_error(getattr(grads, field), fd)
    rows.append((field, str(fd.shape), float(np.max(np.abs(fd))), errors[field]))

# dL/dmeans2d is a stage-level gradient: perturb the 2D means fed to the compositing stage
c = out.cache
bg = np.asarray(config.background)


def loss_from_means2d(m2d):
    o = refgs.composite({**c["g2d"], "means2d": m2d}, c["lists"], W, H, c["profile"], bg)
    return float(np.sum(V_I * o["image"]) + np.sum(V_a * o["alpha"]) + np.sum(V_D * o["depth"]))


fd = fd_gradient(loss_from_means2d, out.means2d)
errors["means2d"] = relative_error(grads.means2d, fd)
rows.append(("means2d (stage)", str(fd.shape), float(np.max(np.abs(fd))), errors["means2d"]))
print(f"central differences, h = {FD_STEP} and h/2, Richardson-extrapolated\n")
print(text_table(rows, ["field", "shape", "max |dL/dfield|", "relative error"]))

# %%
assert all(e < 1e-6 for e in errors.values()), errors
print("every hand-derived gradient agrees with finite differences to better than 1e-6")

# %% [markdown]
# ## The $-0.5$ that is not a bug
#
# The compositing stage needs $\partial L / \partial Q$ for the conic
# $Q = \begin{pmatrix} A & B \\ B & C\end{pmatrix} = \Sigma_{2D}^{-1}$ in
# $\mathrm{power} = -\tfrac12 \Delta^\top Q \Delta$. The off-diagonal $B$ appears **twice** in $Q$.
# There are two honest ways to differentiate (RAS-08, docs/derivations/compositing.md step 7):
#
# * **one variable $B$** (refgs, gsplat): $\partial\,\mathrm{power}/\partial B = -\Delta x\,\Delta y$;
# * **each entry $Q_{01}$ on its own** (the original 3DGS CUDA code):
#   $\partial\,\mathrm{power}/\partial Q_{01} = -\tfrac12 \Delta x\,\Delta y$ — the much-reported
#   "$-0.5$" in `dL_dconic2D.y`. The original then adds the two entries' contributions when it
#   goes on to the 2D covariance (the factor 2 in its `dL_db`), so both conventions give the same
#   numbers down the chain.
#
# Finite differences show both readings on one pixel offset:

# %%
d = np.array([1.7, -0.8])                                   # (dx, dy)
Q = np.array([[0.30, 0.12], [0.12, 0.25]])


def power(Qm):
    return -0.5 * d @ Qm @ d


h = 1e-6
E01 = np.array([[0.0, 1.0], [0.0, 0.0]])                     # one entry
EB = E01 + E01.T                                             # the variable B (both entries)
d_entry = (power(Q + h * E01) - power(Q - h * E01)) / (2 * h)
d_B = (power(Q + h * EB) - power(Q - h * EB)) / (2 * h)
print(f"d power / d Q01 (one entry)  = {d_entry:+.6f}   -0.5 dx dy = {-0.5 * d[0] * d[1]:+.6f}")
print(f"d power / d B   (both)       = {d_B:+.6f}   -1.0 dx dy = {-d[0] * d[1]:+.6f}")

# %% [markdown]
# refgs' compositing backward returns the once-counted $v_B$; a finite difference on the conic's
# $B$ through the compositing stage confirms it for our scene (per-entry gradients would be half
# of it). "Fixing" the original's $-0.5$ to $-1$ while keeping its factor 2 doubles every
# gradient that flows through $B$ — notebook 5 shows the oracle catching exactly that bug.

# %%
vc = refgs.composite_backward(c["g2d"], c["lists"], W, H, c["profile"], bg, out.final_T, V_I, V_a, V_D)


def loss_from_B(b):
    conics = c["g2d"]["conics"].copy()
    conics[:, 1] = b
    o = refgs.composite({**c["g2d"], "conics": conics}, c["lists"], W, H, c["profile"], bg)
    return float(np.sum(V_I * o["image"]) + np.sum(V_a * o["alpha"]) + np.sum(V_D * o["depth"]))


fd_B = fd_gradient(loss_from_B, c["g2d"]["conics"][:, 1])
print("v_B (refgs)         ", vc["v_conics"][:, 1])
print("finite difference   ", fd_B)
print("per-entry (original)", vc["v_conics"][:, 1] / 2)
assert relative_error(vc["v_conics"][:, 1], fd_B) < 1e-6
assert abs(d_entry - (-0.5 * d[0] * d[1])) < 1e-8 and abs(d_B - (-d[0] * d[1])) < 1e-8

# %% [markdown]
# ## What dL/dmean2d looks like
#
# A picture of the gradient the densification heuristic of 3DGS watches (TRN-04): twelve small
# Gaussians, a target image rendered with each of them moved by a known small offset, and the loss
# $L = \tfrac12 \lVert \text{image} - \text{target} \rVert^2$. The arrows are
# $-\partial L/\partial \text{mean2d}$ (white, the direction gradient descent would move each
# 2D mean) and the true 2D offset (yellow).

# %%
rng2 = np.random.default_rng(3)
W2, H2 = 96, 64
cam2 = refgs.Camera.look_at(eye=[0.0, 0.0, -4.0], target=[0.0, 0.0, 0.0], fx=80.0, width=W2, height=H2)
gx, gy = np.meshgrid(np.linspace(-1.5, 1.5, 4), np.linspace(-0.8, 0.8, 3))
n2 = gx.size
sh2 = np.zeros((n2, 1, 3))
sh2[:, 0] = rng2.uniform(-0.8, 1.2, (n2, 3))
scene = refgs.Gaussians(means=np.stack([gx.ravel(), gy.ravel(), rng2.uniform(-0.2, 0.2, n2)], -1),
                        log_scales=np.log(rng2.uniform(0.08, 0.2, (n2, 3))),
                        quats=rng2.normal(size=(n2, 4)), opacity_logits=np.full(n2, 1.5), sh=sh2)
shift = np.concatenate([rng2.uniform(-0.06, 0.06, (n2, 2)), np.zeros((n2, 1))], -1)
target_out = refgs.render(scene.replace(means=scene.means + shift), cam2)
now = refgs.render(scene, cam2)
g2 = refgs.render_backward(now, now.image - target_out.image)
step = -g2.means2d
true_2d = target_out.means2d - now.means2d

fig, ax = plt.subplots(figsize=(7, 4.8))
show_image(ax, 0.5 * (now.image + target_out.image), "current and target, averaged")
p = now.means2d - 0.5                                        # imshow puts pixel centres at integers
scale = 2.0 / np.max(np.linalg.norm(step, axis=1))
ax.quiver(p[:, 0], p[:, 1], step[:, 0] * scale, step[:, 1] * scale, color="w", angles="xy",
          scale_units="xy", scale=1 / 4, width=0.006, label="-dL/dmean2d (rescaled)")
ax.quiver(p[:, 0], p[:, 1], true_2d[:, 0], true_2d[:, 1], color="yellow", angles="xy",
          scale_units="xy", scale=1 / 4, width=0.004, label="true offset (x4)")
ax.legend(fontsize=7, loc="lower right")
plt.show()

cosine = np.sum(step * true_2d, 1) / (np.linalg.norm(step, axis=1) * np.linalg.norm(true_2d, axis=1))
print("cosine between -dL/dmean2d and the true offset, per Gaussian:", cosine.round(2))

# %%
assert np.all(cosine > 0.5), cosine
