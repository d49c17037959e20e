"""Stage probes: small scenes that let one mechanism of the pipeline differ at a time (DEV-03).

A renderer that returns only an image cannot be asked for its covariances or its sort order; it
can be shown scenes where only one mechanism decides the picture.  The probes form a *ladder*:
each names the probe it extends (``base``, the same scene without its one new ingredient) and
the clauses of what it adds, so the outputs *first part* at a probe that differs while its base
agrees (oracle/residual.py).  The root, ``centre``, is one broad isotropic Gaussian at the image
centre: the mean's projection, an isotropic 2D covariance, pixel sampling and one fragment's
alpha.  Every probe is judged through ``render`` (every output the backend returns, image and
alpha at least) against the reference with the candidate deviations on (oracle/explain.py).

    STAGE_PROBES                 name -> StageProbe, in pipeline order (COV, PRJ, SH, RAS)
    stage_probe_cases(profile)   [(StageProbe, Case)] for a backend's declared profile

Scenes are those of refgs.deviations.Witness (camera at the origin looking down +z, f = 16 px,
16 x 16 px unless stated); ``camera_turn`` turns the camera about its y axis by that many
degrees, the Gaussians placed so that they land where ``at`` says.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

import refgs
from refgs.deviations import Witness

from .protocol import Case

#: the pipeline's stages in order (refgs.deviations.Deviation.stage)
STAGE_ORDER = ("COV", "PRJ", "SH", "RAS")
#: what each stage computes, for sentences in the report
STAGE_NAMES = {"COV": "3D covariance (COV)", "PRJ": "projection (PRJ)", "SH": "colour (SH)",
               "RAS": "rasterization (RAS)"}
#: seed of the probes' cases (forward only: no cotangents are drawn)
PROBE_SEED = 1


@dataclass(frozen=True)
class StageProbe:
    """One rung of the ladder: ``witness`` is the scene, ``base`` the probe it extends (None for
    the root), ``clauses`` and ``adds`` what it exercises beyond its base, ``stage`` where that is
    computed, ``claim`` what a difference here says (the report's sentence), ``camera_turn`` a
    camera rotation in degrees (0: identity pose), ``exercises`` the stages a defect of which
    could show here first (default: ``stage`` alone), ``sh_rest`` the degree-2 and degree-3
    coefficients (12 x 3) appended to the witness' degree-1 SH (None: none).  Every Gaussian but those of the rotated
    and off-axis probes lies on the image's centre row, so a 2D covariance without off-diagonal
    term tells a projection defect from the others."""

    name: str
    stage: str
    clauses: tuple
    adds: str
    base: str | None
    witness: Witness
    claim: str = ""
    camera_turn: float = 0.0
    exercises: tuple = ()
    sh_rest: tuple | None = None

    @property
    def could_be(self) -> tuple:
        """The stages whose defect could make this probe differ while its base agrees."""
        return self.exercises or (self.stage,)

    def case(self, profile: str = "inria") -> Case:
        """The probe's scene as a Case (float64) for ``profile``."""
        g, cam, cfg = self.witness.build(profile)
        if self.sh_rest is not None:
            rest = np.broadcast_to(np.asarray(self.sh_rest, np.float64), (len(g), 12, 3))
            g = g.replace(sh=np.concatenate([g.sh, rest], axis=1))
        if self.camera_turn:
            a = np.deg2rad(self.camera_turn)
            R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
            w2c = np.eye(4)
            w2c[:3, :3] = R
            g = g.replace(means=g.means @ R)               # camera-frame means rotated back: R^T p
            cam = refgs.Camera(w2c, cam.K, cam.width, cam.height)
        return Case(g, cam, cfg, seed=PROBE_SEED, label=f"stage probe:{self.name}")


def _logit(o: float) -> float:
    return float(np.log(o / (1.0 - o)))


#: degree-2 and -3 SH coefficients of the view-direction probe: band 3 as strong as band 1, so
#: that a sign slip in one band is not the reversed view direction (which flips every odd band)
_SH_REST = tuple((0.0, 0.0, 0.0) for _ in range(5)) + tuple(
    (0.5 * s, -0.5 * s, 0.25 * s) for s in (1, -1, 1, -1, 1, -1, 1))
#: a broad isotropic Gaussian at the image centre (sigma about 2.4 px)
_CENTRE = Witness(at=((8.0, 8.0, 4.0),), log_scales=(-0.5,), logits=(_logit(0.7),), rgb=((0.7, 0.5, 0.3),))
#: an elongated Gaussian turned about a generic axis, at the centre
_ROTATED = dataclasses.replace(_CENTRE, log_scales=((-0.3, -1.8, -1.2),), quats=((0.8, 0.2, 0.3, 0.45),))
_TWO = dict(log_scales=(-0.3,), logits=(_logit(0.7),), rgb=((0.9, 0.2, 0.1), (0.1, 0.3, 0.9)))

_PROBES = [
    StageProbe("centre", "PRJ", ("PRJ-01", "PRJ-04", "CNV-08", "RAS-03"),
               "one broad isotropic Gaussian at the centre: the mean's projection, an isotropic "
               "2D covariance, pixel sampling, one fragment", None, _CENTRE,
               claim="the simplest scene already differs: the projection of an isotropic Gaussian's "
                     "mean or covariance, pixel sampling or one fragment's alpha departs from "
                     "PRJ-01/PRJ-04/CNV-08/RAS-03",
               exercises=("COV", "PRJ", "SH", "RAS")),
    StageProbe("rotated", "COV", ("COV-01", "CNV-04"),
               "an anisotropic Gaussian with a generic rotation (R S S^T R^T, quaternion order)",
               "centre", _ROTATED,
               claim="the covariance of a rotated Gaussian differs from R S S^T R^T (or the "
                     "quaternion is read in another order)",
               exercises=("COV", "PRJ")),
    StageProbe("rotated_x", "COV", ("COV-01", "CNV-04"),
               "a Gaussian turned about the x axis only, off-axis in y only: the 2D covariance "
               "keeps no off-diagonal term, and its y variance reads Sigma_12 and Sigma_22",
               "centre",
               dataclasses.replace(_ROTATED, at=((8.0, 11.5, 4.0),), quats=((0.866, 0.5, 0.0, 0.0),)),
               claim="the covariance of a Gaussian turned about x differs from R S S^T R^T where no "
                     "2D off-diagonal term is involved: the 3D covariance itself departs"),
    StageProbe("unnormalised", "COV", ("CNV-05",),
               "the same rotation given by a quaternion of norm 2 (normalisation)", "rotated",
               dataclasses.replace(_ROTATED, quats=((1.6, 0.4, 0.6, 0.9),)),
               claim="a quaternion of norm 2 gives another covariance than its normalised rotation"),
    StageProbe("tiny", "PRJ", ("PRJ-04", "PRF-03"),
               "a Gaussian much smaller than a pixel (the 0.3 px^2 dilation dominates)", "centre",
               dataclasses.replace(_CENTRE, at=((8.0, 8.0, 4.0),), log_scales=(-6.0,)),
               claim="a sub-pixel Gaussian differs: the low-pass dilation (+0.3 px^2) or the "
                     "determinant rule departs"),
    StageProbe("rotated_camera", "PRJ", ("PRJ-01", "CNV-02"),
               "the rotated Gaussian seen by a camera turned 35 degrees (W Sigma W^T)", "rotated",
               _ROTATED, claim="a turned camera sees the rotated Gaussian differently: the view "
                               "rotation W Sigma W^T departs",
               camera_turn=35.0),
    StageProbe("off_axis", "PRJ", ("PRJ-03",),
               "an isotropic Gaussian off-axis in x and y inside the frustum (the EWA Jacobian's "
               "off-diagonal terms)", "centre",
               dataclasses.replace(_CENTRE, at=((3.5, 12.5, 3.0),), log_scales=(-0.6,)),
               claim="an off-axis Gaussian's projected ellipse differs: the EWA Jacobian J departs "
                     "off the optical axis"),
    StageProbe("frustum_edge", "PRJ", ("PRJ-03", "PRF-02"),
               "a large Gaussian beyond 1.3 tan(fov/2) with its tail on the image (frustum clamp)",
               "off_axis", Witness(at=((27.2, 8.0, 4.0),), log_scales=(0.3,), logits=(3.0,)),
               claim="a Gaussian beyond the frustum limit differs: the clamp of x/z, y/z to 1.3 "
                     "tan(fov/2) departs"),
    StageProbe("near_plane", "PRJ", ("PRJ-02", "PRF-01"),
               "small Gaussians at depth 0.25 (kept) and 0.1 (culled by the 0.2 near plane)",
               "centre", Witness(at=((5.3, 8.0, 0.25), (11.3, 8.0, 0.1)), log_scales=(-6.0,),
                                 logits=(2.0,)),
               claim="Gaussians near the camera differ: the near-plane cull at t_z <= 0.2 departs"),
    StageProbe("behind_camera", "PRJ", ("PRJ-02",),
               "a Gaussian 3 units behind the camera whose projection lands on the image (culled)",
               "centre", Witness(at=((8.0, 8.0, 4.0), (7.0, 9.0, -3.0)), log_scales=(-0.5, 0.2),
                                 logits=(_logit(0.7), 3.0), rgb=((0.7, 0.5, 0.3), (0.1, 0.9, 0.1))),
               claim="a Gaussian behind the camera is drawn: it must be culled"),
    StageProbe("sh_view", "SH", ("SH-03", "CNV-09"),
               "SH of degree 3 seen off-axis in x (view direction mean - camera, band signs)", "centre",
               dataclasses.replace(_CENTRE, at=((4.0, 8.0, 4.0),),
                                   sh1=((0.3, 0.1, -0.2), (0.2, -0.3, 0.1), (-0.1, 0.2, 0.3))),
               sh_rest=_SH_REST,
               claim="view-dependent colour differs: the SH view direction (mean - camera) or the "
                     "band signs depart"),
    StageProbe("colour_range", "SH", ("CNV-10",),
               "colour channels above 1 and below 0 (the +0.5 offset, the clamp at 0 only)",
               "centre", dataclasses.replace(_CENTRE, rgb=((1.6, -0.4, 1.3),)),
               claim="colours outside [0, 1] differ: the +0.5 offset or the clamp at 0 (only) departs"),
    StageProbe("pixel_centre", "RAS", ("CNV-08",),
               "a small Gaussian on a pixel corner (pixels sampled at j + 0.5, i + 0.5)", "centre",
               Witness(at=((8.0, 8.0, 4.0),), log_scales=(-2.0,)),
               claim="a small Gaussian off the pixel grid differs: pixels are not sampled at their "
                     "centres (j + 0.5, i + 0.5)",
               exercises=("RAS", "PRJ")),
    StageProbe("order_near_first", "RAS", ("RAS-02",),
               "two overlapping Gaussians, the nearer one first in the arrays", "centre",
               Witness(at=((7.0, 8.0, 3.0), (9.0, 8.0, 5.0)), **_TWO),
               claim="two overlapping Gaussians are blended in another order: the front-to-back depth"
                     " sort departs"),
    StageProbe("order_far_first", "RAS", ("RAS-02",),
               "the same two Gaussians, the farther one first in the arrays", "centre",
               Witness(at=((9.0, 8.0, 5.0), (7.0, 8.0, 3.0)), **{**_TWO, "rgb": _TWO["rgb"][::-1]}),
               claim="two overlapping Gaussians given far-first are blended in another order: the "
                     "sort departs (not by depth, or not stable)"),
    StageProbe("sort_key", "RAS", ("RAS-02", "PRJ-06"),
               "two overlapping Gaussians whose order by view-space depth and by distance from "
               "the camera differ (the sort key is t_z)", "order_near_first",
               Witness(at=((8.0, 8.0, 4.0), (0.5, 8.0, 3.7)), log_scales=(0.3,),
                       logits=(_logit(0.8),), rgb=((0.9, 0.2, 0.1), (0.1, 0.3, 0.9))),
               claim="Gaussians whose depth order and distance order differ are blended by distance: "
                     "the sort key is not the view-space depth t_z",
               exercises=("RAS",)),
    StageProbe("low_opacity", "RAS", ("RAS-04",),
               "a broad Gaussian of opacity 0.003 (alpha below 1/255 everywhere: skipped)", "centre",
               dataclasses.replace(_CENTRE, log_scales=(0.0,), logits=(_logit(0.003),)),
               claim="a faint Gaussian (alpha < 1/255) is drawn: the 1/255 skip departs"),
    StageProbe("high_opacity", "RAS", ("RAS-04", "PRF-05"),
               "a broad opaque Gaussian (o G = 0.9997 > the 0.99 cap on the pixels around its "
               "mean, whichever the pixel convention)", "centre",
               Witness(at=((8.0, 8.0, 4.0),), log_scales=(0.5,), logits=(8.0,)),
               claim="an opaque Gaussian differs: the alpha cap of 0.99 departs"),
    StageProbe("deep_stack", "RAS", ("RAS-05", "PRF-06"),
               "six broad opaque Gaussians stacked on the centre (T falls below 1e-4 on many "
               "pixels, at different fragments)", "order_near_first",
               Witness(at=tuple((8.0, 8.0, z) for z in (2.0, 2.8, 3.6, 4.4, 5.2, 6.0)),
                       log_scales=(-1.0,),
                       logits=tuple(_logit(o) for o in (0.95, 0.97, 0.98, 0.98, 0.97, 0.9)),
                       rgb=((0.9, 0.1, 0.1), (0.1, 0.9, 0.1), (0.1, 0.1, 0.9), (0.9, 0.9, 0.1),
                            (0.1, 0.9, 0.9), (0.5, 0.5, 0.5))),
               claim="a deep stack differs: the transmittance stop (T below 1e-4, the saturating "
                     "fragment not blended) departs"),
    StageProbe("background", "RAS", ("RAS-06",),
               "the centre Gaussian over a coloured background (the T bg term)", "centre",
               dataclasses.replace(_CENTRE, background=(0.2, 0.6, 0.9)),
               claim="the background shows differently: the T bg term departs"),
]

#: name -> StageProbe, in pipeline order
STAGE_PROBES: dict[str, StageProbe] = {
    p.name: p for p in sorted(_PROBES, key=lambda p: (p.base is not None, STAGE_ORDER.index(p.stage)))}


def stage_probe_cases(profile: str = "inria", names=None) -> list[tuple[StageProbe, Case]]:
    """[(probe, its Case)] for ``profile``, in ladder order (``names``: a subset, default all)."""
    return [(p, p.case(profile)) for n, p in STAGE_PROBES.items() if names is None or n in names]


def base_chain(name: str) -> list[str]:
    """The probes ``name`` extends, nearest first (``rotated_camera`` -> [rotated, centre])."""
    out, p = [], STAGE_PROBES[name].base
    while p is not None:
        out.append(p)
        p = STAGE_PROBES[p].base
    return out


__all__ = ["PROBE_SEED", "STAGE_NAMES", "STAGE_ORDER", "STAGE_PROBES", "StageProbe", "base_chain",
           "stage_probe_cases"]
