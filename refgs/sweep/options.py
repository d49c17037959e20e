"""The options of ``refgs train``, by long name: one table for the command line (refgs.cli) and
for grid files (refgs.sweep.grid), so that a grid accepts exactly the options ``refgs train``
accepts, with the same types, choices and defaults (docs/spec/training.md TRN-07).

    add_train_options(parser)    every ``refgs train`` option, added to an argparse parser
    config_from_args(args)       the TrainConfig of a new run from the parsed options
"""
from __future__ import annotations

import argparse

from ..backends import TRAIN_PREFERENCE, available_backends, default_backend
from ..errors import ConfigError
from ..methods import METHOD_NAMES, method_params
from ..methods.flat_minima import CLAMP_MODES, PERTURB_TARGETS
from ..train.densify import DENSIFY_PRESETS, SCREEN_SIZE_RULES
from ..train.loss import LOSS_FORMS
from ..train.schedule import SH_MAX_DEGREE
from ..train.strategy import COMPACT_PRESET, CompactConfig, parse_resolution_schedule
from ..train.trainer import BACKGROUNDS, DTYPES, TrainConfig

#: Flags a new run needs (``--resume`` takes them from the run's config.json instead).
NEW_RUN_FLAGS = ("scene", "views", "iters", "out")
#: Densification flags (argparse dest) that override the chosen --densify-preset.
DENSIFY_FLAGS = ("start", "interval", "until", "grad_threshold", "opacity_reset_interval",
                 "screen_size_rule")
#: Method flags (argparse dest = the recorded parameter name; refgs.methods.method_params).
METHOD_FLAGS = ("gamma", "p", "p_ramp", "schedule", "clamp", "noise", "noise_fixed_sigma",
                "perturb", "mixed_loss", "reinit", "reinit_interval", "reinit_window", "r_max")
#: Compact-strategy flags (argparse dest = the CompactConfig field; TRN-14).
COMPACT_FLAGS = ("budget", "prune_fraction", "prune_every", "final_prune_fraction",
                 "resolution_schedule")
#: Options that say where and how to run, not what: they are not settings of a run.
RUN_CONTROL_FLAGS = ("resume", "out", "quiet")


def add_train_options(t: argparse.ArgumentParser) -> None:
    """Add every ``refgs train`` option to ``t`` (the flat-minima and densification options in
    argument groups of their own)."""
    t.add_argument("--resume", metavar="RUN_DIR", help="continue an interrupted run")
    t.add_argument("--scene", help="scene folder (sparse/0 + image folder)")
    t.add_argument("--images", default="images_8", help="image folder inside the scene")
    t.add_argument("--resolution", type=float, help="downsampling factor >= 1 applied on load")
    t.add_argument("--views", type=int, help="number of training views")
    t.add_argument("--method", default="3dgs", choices=sorted(METHOD_NAMES))
    t.add_argument("--iters", type=int, help="iterations T (all schedule horizons use T)")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--backend",
                   help=f"one of {', '.join(available_backends())}, or module:object (default: "
                        f"the first of {', '.join(TRAIN_PREFERENCE)} that loads here: fast when "
                        f"numba imports; the run records the name)")
    t.add_argument("--out", help="run directory to create")
    t.add_argument("--init-points", default="train-views", metavar="train-views|sfm-all|PATH.ply")
    t.add_argument("--checkpoint-every", type=int, default=1000, metavar="K", help="0: only on Ctrl-C")
    t.add_argument("--eval-every", type=int, metavar="K",
                   help="test PSNR every K (default T/10; 0: end only)")
    t.add_argument("--strict", action="store_true", help="unmatched images/model entries are errors")
    t.add_argument("--dtype", default="float32", choices=sorted(DTYPES),
                   help="training dtype (default float32, as GPU implementations train; float64: "
                        "the reference's exact arithmetic; docs/performance.md)")
    t.add_argument("--background", default="black", choices=sorted(BACKGROUNDS))
    t.add_argument("--loss-form", default="l1_plus", choices=LOSS_FORMS)
    t.add_argument("--lambda-dssim", type=float, default=0.2)
    t.add_argument("--no-clamp", action="store_true", help="do not clamp the render before the loss")
    t.add_argument("--profile", default="inria", choices=("inria", "gsplat"))
    t.add_argument("--sh-degree", type=int, help=f"largest SH degree (default {SH_MAX_DEGREE}; "
                   f"--compact: {COMPACT_PRESET['sh_degree']})")
    t.add_argument("--holdout", type=int, default=8, help="every k-th view is a test view")
    t.add_argument("--triangulation", default="tuned", help="preset for --init-points train-views")
    t.add_argument("--no-lpips", action="store_true", help="skip LPIPS in the final evaluation")
    t.add_argument("--quiet", action="store_true", help="no progress bar or table")
    f = t.add_argument_group("flat-minima method (docs/spec/method.md) and DropGaussian")
    f.add_argument("--fm", action="store_true", help="add the flat-minima method (with --method dropgaussian: the plug-in)")
    f.add_argument("--fm-gamma", type=float, dest="gamma", help="perturbation coefficient (default 2)")
    f.add_argument("--fm-p", type=float, dest="p", help="perturbation probability (default 0.3)")
    f.add_argument("--fm-p-ramp", action="store_true", dest="p_ramp", default=None, help="ramp p as p t/T")
    f.add_argument("--fm-no-schedule", action="store_false", dest="schedule", default=None,
                   help="alpha(t) = 1 instead of t/T")
    f.add_argument("--fm-clamp", choices=CLAMP_MODES, dest="clamp", help="clamp reading (default axis)")
    f.add_argument("--fm-noise", choices=("anisotropic", "iso_max", "iso_mean", "iso_fixed"), dest="noise",
                   help="noise shape (ablation; iso_fixed: half the densification size threshold)")
    f.add_argument("--fm-noise-sigma", type=float, dest="noise_fixed_sigma",
                   help="with --fm-noise iso_fixed: this standard deviation instead")
    f.add_argument("--fm-perturb", choices=PERTURB_TARGETS, dest="perturb",
                   help="perturbed parameter (ablation; default position)")
    f.add_argument("--fm-mixed-loss", action="store_true", dest="mixed_loss", default=None,
                   help="ablation: average the gradients of a fully perturbed and a clean render")
    f.add_argument("--fm-no-reinit", action="store_false", dest="reinit", default=None, help="no periodic reinit")
    f.add_argument("--fm-reinit-interval", type=int, dest="reinit_interval")
    f.add_argument("--fm-reinit-window", type=int, dest="reinit_window")
    f.add_argument("--drop-r-max", type=float, dest="r_max", help="DropGaussian's largest drop rate (0.2)")
    d = t.add_argument_group("densification")
    d.add_argument("--densify-preset", default="dropgaussian", choices=sorted(DENSIFY_PRESETS))
    d.add_argument("--densify-from", type=int, dest="start")
    d.add_argument("--densify-interval", type=int, dest="interval")
    d.add_argument("--densify-until", type=int, dest="until")
    d.add_argument("--densify-grad-threshold", type=float, dest="grad_threshold")
    d.add_argument("--opacity-reset-interval", type=int, dest="opacity_reset_interval")
    d.add_argument("--screen-size-rule", choices=SCREEN_SIZE_RULES, dest="screen_size_rule")
    c = t.add_argument_group("compact strategy (docs/spec/training.md TRN-14, docs/compact.md)")
    c.add_argument("--compact", action="store_true",
                   help="the recommended compact preset (its values: refgs.train.strategy."
                        "COMPACT_PRESET); the flags below override it")
    c.add_argument("--budget", type=int, help="at most this many Gaussians")
    c.add_argument("--prune-fraction", type=float, help="soft pruning: fraction of least "
                   "contribution removed every --prune-every iterations while densifying")
    c.add_argument("--prune-every", type=int, metavar="K")
    c.add_argument("--final-prune-fraction", type=float, help="hard pruning once densification ends")
    c.add_argument("--resolution-schedule", metavar="S:F,...",
                   help="fit images downsampled by F from iteration S*T on (e.g. 0:4,0.3:2,0.6:1)")


def compact_from_args(args) -> tuple:
    """(CompactConfig or None, densify overrides, SH degree) of the parsed compact flags: None
    and the paper's values when neither --compact nor a compact flag is given (TRN-14)."""
    given = {k: getattr(args, k) for k in COMPACT_FLAGS if getattr(args, k, None) is not None}
    if "resolution_schedule" in given:
        given["resolution_schedule"] = parse_resolution_schedule(given["resolution_schedule"])
    sh = args.sh_degree
    if not args.compact and not given:
        return None, {}, SH_MAX_DEGREE if sh is None else sh
    base = COMPACT_PRESET if args.compact else {}
    compact = CompactConfig(**{**base.get("compact", {}), **given})
    until = None
    if "densify_until" in base and args.iters is not None:
        until = int(base["densify_until"] * args.iters)
    sh = sh if sh is not None else base.get("sh_degree", SH_MAX_DEGREE)
    return compact, {"until": until}, sh


def config_from_args(args) -> TrainConfig:
    """TrainConfig of a new run from parsed ``refgs train`` arguments."""
    for flag in NEW_RUN_FLAGS:
        if getattr(args, flag) is None:
            raise ConfigError(f"--{flag}: required for a new run (or give --resume RUN_DIR)")
    given = {k: getattr(args, k) for k in METHOD_FLAGS if getattr(args, k, None) is not None}
    compact, compact_densify, sh_degree = compact_from_args(args)
    densify = {k: getattr(args, k) for k in DENSIFY_FLAGS}
    densify.update({k: v for k, v in compact_densify.items() if densify.get(k) is None})
    return TrainConfig.with_preset(
        args.densify_preset, densify,
        scene=args.scene, views=args.views, iters=args.iters, seed=args.seed, images=args.images,
        resolution=args.resolution, method=args.method,
        method_params=method_params(args.method, given, fm=bool(args.fm)),
        backend=args.backend or default_backend(),
        init_points=args.init_points, checkpoint_every=args.checkpoint_every,
        eval_every=args.eval_every, strict=args.strict, dtype=args.dtype, profile=args.profile,
        sh_degree=sh_degree, compact=compact, background=args.background, loss_form=args.loss_form,
        lambda_dssim=args.lambda_dssim, clamp_render=not args.no_clamp, holdout=args.holdout,
        triangulation=args.triangulation, lpips=not args.no_lpips)


__all__ = ["add_train_options", "config_from_args", "compact_from_args", "NEW_RUN_FLAGS",
           "DENSIFY_FLAGS", "METHOD_FLAGS", "COMPACT_FLAGS", "RUN_CONTROL_FLAGS"]
