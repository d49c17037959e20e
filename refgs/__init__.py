"""refgs: the executable specification of 3D Gaussian Splatting (numpy, float64 by default).

Public API (clause ids in docs/spec/):

    Gaussians, Camera, RenderConfig, RenderOutput, Gradients   -- containers (API-01..API-05)
    render(gaussians, camera, config) -> RenderOutput           -- forward (all stages)
    render_backward(out, v_image, v_alpha=None, v_depth=None)   -- hand-derived backward
    covariance_3d, project_gaussians, eval_sh_colors, ...       -- the stages, by name

Above the spec (imported on use, not by ``import refgs``; docs/architecture.md):

    refgs.backends   the backend registry: a name or module:object -> a renderer
    refgs.runs       run directories: train, resume, load, evaluate, render
"""
__version__ = "0.1.0"
#: version of the written spec (docs/spec/); carried by the oracle's reports
SPEC_VERSION = "0.1"

from .types import Camera, Gaussians, Gradients, RenderConfig, RenderOutput  # noqa: E402
from .constants import GSPLAT, INRIA, PROFILES, Profile, get_profile  # noqa: E402
from .covariance import covariance_3d, covariance_3d_backward, quat_to_rotmat, normalize_quats  # noqa: E402
from .projection import project_gaussians, project_gaussians_backward, world_to_camera, tile_rectangles  # noqa: E402
from .sh import eval_sh_colors, eval_sh_colors_backward, sh_basis, num_sh_coeffs  # noqa: E402
from .rasterize import build_tile_lists, composite, composite_backward  # noqa: E402
from .render import render, render_backward, validate_inputs, validate_gaussians  # noqa: E402
from .activations import raw_gradients, to_activated  # noqa: E402


def __getattr__(name: str):
    """``refgs.sap_offsets`` (FM-01), the paper's perturbation, imported on first use so that
    ``import refgs`` loads the spec alone (not the method and training rooms above it)."""
    if name == "sap_offsets":
        from .methods.flat_minima import sap_offsets
        return sap_offsets
    raise AttributeError(f"module 'refgs' has no attribute {name!r}")


__all__ = [
    "Camera", "Gaussians", "Gradients", "RenderConfig", "RenderOutput",
    "GSPLAT", "INRIA", "PROFILES", "Profile", "get_profile",
    "covariance_3d", "covariance_3d_backward", "quat_to_rotmat", "normalize_quats",
    "project_gaussians", "project_gaussians_backward", "world_to_camera", "tile_rectangles",
    "eval_sh_colors", "eval_sh_colors_backward", "sh_basis", "num_sh_coeffs",
    "build_tile_lists", "composite", "composite_backward",
    "render", "render_backward", "validate_inputs", "validate_gaussians", "sap_offsets",
    "to_activated", "raw_gradients",
]
