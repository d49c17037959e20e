"""Template for a new oracle backend -- copy this file, fill in the TODOs, then run

    python -m oracle check --backend my_backend:backend

(docs/oracle.md walks through certifying a backend start to finish).  As shipped, the template
delegates every call to refgs in float32, so it passes the oracle and shows the expected shapes;
replace each delegation with a call into your renderer.

The contract (oracle/protocol.py, ORC-01):

* ``render(gaussians, camera, config)`` gets refgs containers holding float64 arrays whose values
  are exactly representable in your ``dtype``.  Return an object or dict with at least ``image``
  (H, W, 3) and ``alpha`` (H, W) in your dtype; add ``depth``, ``n_contrib``, ``radii``,
  ``means2d``, ``depths``, ``conics``, ``colors``, ``opacities``, ``visible`` if you have them --
  each one you return is compared, each one you leave out is reported as not provided.
* Raise ``ValueError`` on invalid input (a zero quaternion, NaN, wrong shapes, a non-rigid pose,
  fx <= 0) (API-03).
* ``render_backward(out, v_image, v_alpha=None, v_depth=None)`` (optional) returns dL/d(raw
  parameters): means, log_scales, quats, opacity_logits, sh, and optionally means2d in pixels.
  If your renderer takes activated parameters, map your gradients back with
  :func:`oracle.protocol.raw_gradients`.
* The helpers ``to_activated`` and ``raw_gradients`` work in the dtype of the Gaussians they are
  given.  The oracle hands you float64 arrays (holding values exact in your dtype): cast first,
  ``gaussians.astype(self.dtype)``, and pass the cast Gaussians to both helpers, or a float32
  backend returns float64 gradients and fails ``backward_dtype`` (CNV-11).
* Capabilities are plain attributes (below).  Checks outside them report "n/a" with the reason,
  and the oracle draws no case outside them (SH degree, camera model, principal point,
  background, opacity_scale, antialiasing).
* Differences you know of and accept can be declared in ``known_differences`` (check, clause,
  reason, link): they are reported as "known", not as failures, until they stop happening.
* Stage functions (``stage_covariance``, ``stage_projection``, ``stage_sh``,
  ``stage_composite``) are optional; each one you define gets a per-stage check.
"""
from __future__ import annotations

import numpy as np

import refgs
from refgs.activations import raw_gradients, to_activated


class TemplateBackend:
    """A backend skeleton: every method says what to return."""

    # ---- capabilities (required: profile, dtype) -----------------------------------------------
    profile = "inria"              # TODO: "inria" (original 3DGS) or "gsplat" (gsplat 1.5.3)
    dtype = "float32"              # TODO: the dtype your renderer computes in
    name = "template (refgs float32 inside)"   # TODO: shown in the report
    version = refgs.__version__    # TODO: your renderer's version
    max_sh_degree = 3              # TODO: the highest SH degree you render
    supports_antialiased = False   # TODO: gsplat's rasterize_mode="antialiased" (gsplat profile only)
    supports_opacity_scale = True  # TODO: RenderConfig.opacity_scale (per-Gaussian opacity factor)
    supports_background = True     # TODO: False if you render on black only (RenderConfig.background)
    supports_principal_point = True  # TODO: False if you assume cx = W/2, cy = H/2
    camera_model = "pinhole"       # TODO: "simple_pinhole" if you take one focal length (fx == fy)
    known_differences = ()         # TODO: e.g. ({"check": "forward_coverage", "clause": "PRF-04",
    #                                  "reason": "...", "link": "https://..."},)

    def render(self, gaussians: refgs.Gaussians, camera: refgs.Camera, config: refgs.RenderConfig):
        """TODO: call your renderer.  Typical conversion for an activated-parameter renderer:

            p = to_activated(gaussians)        # means, scales, unit quats, opacities, sh
            K = np.asarray(camera.K); w2c = np.asarray(camera.world_to_camera)
            image, alpha = my_renderer(p["means"].astype(self.dtype), ..., w2c, K,
                                       camera.width, camera.height, config.background)

        Pixel (row i, column j) must be sampled at image coordinates (j + 0.5, i + 0.5) (CNV-08).
        """
        if len(gaussians) and np.any(~np.any(np.asarray(gaussians.quats) != 0, axis=-1)):
            raise ValueError("Gaussians.quats: zero quaternion (CNV-05)")
        g = gaussians.astype(self.dtype)   # your dtype first: the helpers keep the dtype they get
        to_activated(g)               # shows the helper; validates quaternions the same way
        out = refgs.render(g, camera, config)
        return {"image": out.image, "alpha": out.alpha, "depth": out.depth,
                "n_contrib": out.n_contrib, "radii": out.radii, "means2d": out.means2d,
                "depths": out.depths, "conics": out.conics, "colors": out.colors,
                "_native": out, "_gaussians": g}   # anything else you need for the backward

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        """TODO: gradients of L = <v_image, image> + <v_alpha, alpha> + <v_depth, depth>.

        With activated-parameter gradients v_means, v_scales, v_quats (w.r.t. the unit
        quaternion), v_opacities, v_sh from your renderer, and the Gaussians *cast to your
        dtype* in render (``out["_gaussians"]``; with the oracle's float64 Gaussians the
        gradients would come back float64):

            return raw_gradients(out["_gaussians"], v_means, v_scales, v_quats, v_opacities, v_sh,
                                 v_means2d=v_means2d_pixels, quats_were_unit=True)
        """
        native = out["_native"]
        return refgs.render_backward(native, v_image, v_alpha, v_depth)


#: the object to pass as --backend oracle.adapters.template:backend
backend = TemplateBackend()

__all__ = ["TemplateBackend", "backend", "raw_gradients", "to_activated"]
