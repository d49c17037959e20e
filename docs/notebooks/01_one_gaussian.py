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
# # 1. One Gaussian, from parameters to pixels
#
# A 3D Gaussian splat is five arrays of raw parameters. `refgs.render` turns them into an image
# in four stages, and each stage is a plain numpy function you can call on its own:
#
# | stage | function | spec |
# |---|---|---|
# | quaternion + log-scale → 3D covariance $\Sigma = R S S^\top R^\top$ | `refgs.covariance_3d` | COV-01 |
# | world → camera → EWA projection: 2D mean, 2D covariance, radius, tiles | `refgs.project_gaussians` | PRJ-01..PRJ-05 |
# | spherical harmonics → view-dependent colour | `refgs.eval_sh_colors` | SH-01..SH-03 |
# | depth sort, tile lists, front-to-back alpha compositing | `refgs.build_tile_lists`, `refgs.composite` | RAS-01..RAS-06 |
#
# This notebook follows **one** Gaussian through all four, with a plot for each, and checks at the
# end that calling the stages by hand gives exactly what `refgs.render` gives.
# Conventions (docs/spec/conventions.md): OpenCV camera (x right, y down, z forward), pixel
# (row i, column j) sampled at image coordinates (j + 0.5, i + 0.5).

# %%
import matplotlib.pyplot as plt
import numpy as np
from scipy.special import expit

import refgs

# helpers beside this notebook (docs/notebooks/_helpers.py)
from _helpers import add_ellipse, cov2d_matrix, draw_tiles, show_image

# %% [markdown]
# ## The parameters
#
# One Gaussian, elongated along its first axis, rotated 40° about a tilted axis, fairly opaque,
# with degree-1 spherical harmonics (4 coefficients per colour channel) so that its colour
# depends on where it is seen from. The camera sits 4 units in front of it.

# %%
axis = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
half = np.radians(40.0) / 2
quat = np.concatenate([[np.cos(half)], np.sin(half) * axis])          # (w, x, y, z), CNV-04

sh = np.zeros((1, 4, 3))
sh[0, 0] = [0.9, 0.2, -0.6]            # DC: orange-ish once the +0.5 offset is added (CNV-10)
sh[0, 2] = [0.0, 0.0, 0.8]             # Y_1,0 ~ z: bluer when the view direction has z > 0
sh[0, 3] = [0.9, -0.3, 0.0]            # Y_1,+1 ~ -x: redder when the view direction has x < 0

g = refgs.Gaussians(means=[[0.6, -0.3, 0.0]],
                    log_scales=np.log([[0.35, 0.12, 0.06]]),
                    quats=[quat],
                    opacity_logits=[2.0],
                    sh=sh)
W, H = 96, 64
cam = refgs.Camera.look_at(eye=[0.0, 0.0, -4.0], target=[0.0, 0.0, 0.0], fx=60.0, width=W, height=H)
print("opacity = sigmoid(2.0) =", expit(2.0))
print("camera centre", cam.center)

# %% [markdown]
# ## Stage 1: the 3D covariance
#
# $R$ is the rotation of the normalised quaternion, $S = \mathrm{diag}(e^{\text{log-scales}})$, and
# $\Sigma = R S S^\top R^\top$. The surface $\{x : (x-\mu)^\top \Sigma^{-1} (x-\mu) = 1\}$ is the
# 1-sigma ellipsoid. Below: its slices through the mean by the three coordinate planes (solid),
# the shadows it casts on them (the marginal, $\Sigma$ restricted to the two coordinates; dashed),
# and the principal axes $s_k R_{:,k}$.

# %%
cov = refgs.covariance_3d(g.quats, g.log_scales)
Sigma, R, s = cov["cov3d"][0], cov["R"][0], cov["scales"][0]
print("scales", s)
print("Sigma =\n", Sigma.round(4))
Sigma_inv = np.linalg.inv(Sigma)

fig, axes = plt.subplots(1, 3, figsize=(11, 3.6))
names = "xyz"
for ax, (i, j) in zip(axes, [(0, 1), (0, 2), (1, 2)]):
    idx = [i, j]
    slice_cov = np.linalg.inv(Sigma_inv[np.ix_(idx, idx)])   # the slice through the mean
    add_ellipse(ax, (0, 0), slice_cov, color="tab:blue", label="slice")
    add_ellipse(ax, (0, 0), Sigma[np.ix_(idx, idx)], color="tab:gray", ls="--", label="shadow")
    for k, c in zip(range(3), ["tab:red", "tab:green", "tab:purple"]):
        v = s[k] * R[idx, k]
        ax.plot([0, v[0]], [0, v[1]], color=c, lw=2, label=f"$s_{k} R_{{:,{k}}}$")
    ax.set_xlim(-0.4, 0.4)
    ax.set_ylim(-0.4, 0.4)
    ax.set_aspect("equal")
    ax.set_xlabel(names[i])
    ax.set_ylabel(names[j])
    ax.set_title(f"{names[i]}{names[j]} plane through the mean", fontsize=9)
axes[0].legend(fontsize=7, loc="lower left")
plt.tight_layout()
plt.show()

# %% [markdown]
# ## Stage 2: projection
#
# The mean goes to camera space, $t = R_w \mu + t_w$, and then to the image,
# $(f_x t_x/t_z + c_x,\ f_y t_y/t_z + c_y)$. The covariance is projected with the Jacobian $J$ of
# that map at $t$ (EWA splatting): $\Sigma_{2D} = J R_w \Sigma R_w^\top J^\top$, plus a 0.3 px² dilation
# on the diagonal (PRJ-04). The original 3DGS then takes a radius of $\lceil 3\sqrt{\lambda_{\max}}\rceil$
# pixels (PRF-04) and lists the Gaussian in every 16×16 tile that the square of that radius
# touches (RAS-01). Only pixels of those tiles evaluate the Gaussian. Beyond the square the
# Mahalanobis distance is at least 3, so the alpha lost there is at most $o\,e^{-4.5} \approx 0.01$:
# small, but not always below the $1/255$ skip threshold, which is why the tile rule is part of
# the model and two backends with different tile rules differ in the image (PRF-08).

# %%
profile = refgs.INRIA
proj = refgs.project_gaussians(g.means, cov["cov3d"], expit(g.opacity_logits), cam, profile)
mean2d, cov2d = proj["means2d"][0], cov2d_matrix(proj["cov2d"][0])
radius = int(proj["radii"][0, 0])
rect = proj["tile_rect"][0]
print("camera-space mean t =", proj["t"][0].round(4), " depth =", proj["depths"][0])
print("J =\n", proj["J"][0].round(3))
print("2D mean (px)", mean2d.round(3), " 2D covariance (px^2)\n", cov2d.round(3))
print("radius", radius, "px; tiles x", rect[0], "..", rect[1] - 1, ", y", rect[2], "..", rect[3] - 1)

fig, ax = plt.subplots(figsize=(6, 4.5))
draw_tiles(ax, W, H, rect)
add_ellipse(ax, mean2d, cov2d, 1.0, color="tab:blue", label="1 sigma")
add_ellipse(ax, mean2d, cov2d, 3.0, color="tab:blue", ls="--", label="3 sigma")
ax.add_patch(plt.Rectangle(mean2d - radius, 2 * radius, 2 * radius, fill=False, color="tab:red",
                           label=f"radius {radius} px (square)"))
ax.plot(*mean2d, "k+", ms=10)
ax.set_xlim(0, W)
ax.set_ylim(H, 0)                      # image rows grow downwards
ax.set_aspect("equal")
ax.set_title("projected ellipse, radius and covered tiles (shaded)", fontsize=9)
ax.legend(fontsize=7, loc="lower right")
plt.show()

# %% [markdown]
# ## Stage 3: colour from spherical harmonics
#
# The colour is $\max(\sum_k Y_k(d)\, c_k + 0.5,\ 0)$ per channel, with $d$ the unit direction
# from the camera centre to the mean (SH-03, CNV-10). Walking the camera around the Gaussian on a
# horizontal circle changes $d$ and therefore the colour. Our camera is at azimuth 0. Where a
# channel would go negative it is clamped at 0 (the flat stretch of the blue curve); there is no
# clamp at 1.

# %%
az = np.radians(np.linspace(-180, 180, 181))
campos = g.means[0] + 4.0 * np.stack([np.sin(az), np.zeros_like(az), -np.cos(az)], -1)
colours = np.stack([refgs.eval_sh_colors(g.means, g.sh, c, degree=1)["colors"][0] for c in campos])
here = refgs.eval_sh_colors(g.means, g.sh, cam.center, degree=1)

fig, (ax, strip) = plt.subplots(2, 1, figsize=(7, 3.6), height_ratios=[4, 1], sharex=True)
for ch, c in enumerate(["tab:red", "tab:green", "tab:blue"]):
    ax.plot(np.degrees(az), colours[:, ch], color=c, label="RGB"[ch])
ax.axvline(0.0, color="k", ls=":", label="our camera")
ax.axhline(0.0, color="0.5", lw=0.8)
ax.set_ylabel("colour")
ax.legend(fontsize=7, ncol=4)
strip.imshow(np.clip(colours, 0, 1)[None], aspect="auto", extent=[-180, 180, 0, 1])
strip.set_yticks([])
strip.set_xlabel("camera azimuth around the Gaussian (degrees)")
plt.tight_layout()
plt.show()
print("colour seen by our camera:", here["colors"][0].round(4),
      " clamped channels:", here["clamped"][0])

# %% [markdown]
# ## Stage 4: compositing
#
# Per pixel, the Gaussians of its tile are visited front to back; each contributes
# $\alpha = \min(0.99,\ o\, e^{\mathrm{power}})$ with $\mathrm{power} = -\tfrac12 \Delta^\top \Sigma_{2D}^{-1} \Delta$
# (fragments below $1/255$ are skipped), weighted by the transmittance $T$ left by the ones in front
# (RAS-03..RAS-06). With a single Gaussian, $T = 1$, so the image is $\alpha\,c$, the alpha map is
# $\alpha$, and the depth map is $\alpha\, t_z$: depth / alpha, the expected depth, is $t_z = 4$
# wherever the Gaussian is seen. The dashed line is the 3-sigma ellipse.

# %%
g2d = {"means2d": proj["means2d"], "conics": proj["conics"], "opacities": expit(g.opacity_logits),
       "colors": here["colors"], "depths": proj["depths"]}
lists = refgs.build_tile_lists(proj["tile_rect"], proj["depths"], proj["visible"], W, H)
comp = refgs.composite(g2d, lists, W, H, profile, background=np.zeros(3))

fig, axes = plt.subplots(1, 3, figsize=(12, 3.2))
show_image(axes[0], comp["image"], "image")
im = show_image(axes[1], comp["alpha"], "alpha", cmap="gray", vmin=0, vmax=1)
plt.colorbar(im, ax=axes[1], fraction=0.04)
im = show_image(axes[2], comp["depth"], "depth (sum of a T z, unnormalised)", cmap="viridis")
plt.colorbar(im, ax=axes[2], fraction=0.04)
for ax in axes:
    add_ellipse(ax, mean2d - 0.5, cov2d, 3.0, color="w", ls="--", lw=0.8)   # imshow: pixel i at i
plt.tight_layout()
plt.show()

# %% [markdown]
# ## Checks
#
# The stages called by hand are exactly `refgs.render`; alpha peaks just below the opacity; every
# pixel the Gaussian reaches lies in a covered tile; and with one Gaussian the expected depth is
# its camera depth everywhere.

# %%
out = refgs.render(g, cam, refgs.RenderConfig(profile="inria"))
assert np.array_equal(out.image, comp["image"]) and np.array_equal(out.alpha, comp["alpha"])
assert np.array_equal(out.depth, comp["depth"])

o = expit(2.0)
assert 0.95 * o < out.alpha.max() <= o, out.alpha.max()

tile_mask = np.zeros((H, W), bool)
x0, x1, y0, y1 = rect
tile_mask[y0 * 16:y1 * 16, x0 * 16:x1 * 16] = True
assert np.all(out.alpha[~tile_mask] == 0) and np.any(out.alpha[tile_mask] > 0)

hit = out.alpha > 0
assert np.allclose(out.depth[hit] / out.alpha[hit], proj["depths"][0], rtol=1e-12)
assert np.allclose(out.image, out.alpha[..., None] * out.colors[0], rtol=1e-12, atol=0)
print("all checks passed")
