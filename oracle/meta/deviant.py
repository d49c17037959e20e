"""Deviant backends: refgs with named deviations switched on (docs/spec/deviations.md).

The diagnosis (oracle/diagnose.py) must recover exactly the deviations a backend was built with
(tests/test_diagnose.py).  A deviant backend is refgs rendering with
``RenderConfig(deviations=...)``; it declares a profile and a dtype like any backend, exposes
render and render_backward but no stage functions, and never modifies refgs.

    DeviantBackend(deviations, profile="inria", dtype="float64", renders_as=None)
    deviant(*names)                    refgs (inria, float64) with ``names`` on
    gsplat_as_inria                    refgs' gsplat profile declared as "inria"
    four_deviations, no_dilation_float32   examples for ``python -m oracle diagnose``
    two_deviations                     the shrinker keeps each failure's own deviation
    random_combinations(seed, count)   seeded compatible pairs and triples of observable deviations
"""
from __future__ import annotations

import dataclasses

import numpy as np

import refgs
from refgs.deviations import DEVIATIONS, check_deviations, incompatible


class DeviantBackend:
    """refgs at ``dtype`` with ``deviations`` on, declaring ``profile`` (ORC-01); it renders
    with the profile ``renders_as`` (default: the declared one)."""

    max_sh_degree = refgs.constants.SH_MAX_DEGREE
    has_backward = True
    supports_opacity_scale = True

    def __init__(self, deviations=(), profile: str = "inria", dtype: str = "float64",
                 renders_as: str | None = None):
        self.deviations = check_deviations(deviations, "DeviantBackend.deviations")
        self.profile, self.dtype = profile, dtype
        self.renders_as = renders_as or profile
        self.supports_antialiased = profile == "gsplat" and self.renders_as == "gsplat"
        what = ", ".join(sorted(self.deviations)) or "no deviation"
        self.name = f"refgs-{self.renders_as}-{dtype} + {what}"
        self.version = refgs.__version__

    def render(self, gaussians, camera, config=None):
        config = refgs.RenderConfig(profile=self.profile) if config is None else config
        config = dataclasses.replace(config, profile=self.renders_as, deviations=self.deviations)
        return refgs.render(gaussians.astype(self.dtype), camera, config)

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        return refgs.render_backward(out, v_image, v_alpha, v_depth)


def deviant(*names: str) -> DeviantBackend:
    """refgs (inria profile, float64) with the named deviations on."""
    return DeviantBackend(frozenset(names))


#: refgs' gsplat profile judged as the inria profile: its differences are the gsplat choices
gsplat_as_inria = DeviantBackend(frozenset(), profile="inria", renders_as="gsplat")
#: four departures at once: no dilation, no frustum clamp, no 1/255 skip, a transposed rotation
four_deviations = deviant("no_dilation", "no_frustum_clamp", "alpha_skip_off", "rotation_transposed")
#: refgs at float32 without the 0.3 dilation (the diagnosis judged against float32 tolerances)
no_dilation_float32 = DeviantBackend(frozenset({"no_dilation"}), dtype="float32")
#: two departures that show in different checks: colours clamped to [0, 1] (forward_sh,
#: forward_colour_clamp) and no frustum clamp (forward_frustum_clamp): the minimal case of each
#: failing check keeps its own deviation (ORC-06 with DEV-02, tests/test_diagnose.py)
two_deviations = deviant("colour_clamp_01", "no_frustum_clamp")


def observable_names() -> list[str]:
    """Deviations a witness scene can show, in catalogue order."""
    return [n for n, d in DEVIATIONS.items() if d.observable]


def random_combinations(seed: int, count: int, sizes=(2, 3)) -> list[frozenset]:
    """``count`` distinct compatible sets of observable deviations, sizes drawn from ``sizes``,
    from ``np.random.default_rng(seed)`` (the same seed gives the same sets)."""
    rng = np.random.default_rng(seed)
    names = observable_names()
    out: list[frozenset] = []
    while len(out) < count:
        size = int(rng.choice(sizes))
        pick = frozenset(rng.choice(names, size=size, replace=False).tolist())
        if incompatible(pick) is None and pick not in out:
            out.append(pick)
    return out


__all__ = ["DeviantBackend", "deviant", "four_deviations", "gsplat_as_inria",
           "no_dilation_float32", "observable_names", "random_combinations", "two_deviations"]
