"""The training loop of 3DGS as the sparse-view papers run it (clauses TRN-01..TRN-09).

The data flow of one iteration t (1-based, as 3DGS ``train.py``@82bc469; peers.md 1.6, 1.7, 3.1),
``Trainer.step``::

    scene view, background        pop a view from the shuffled stack; draw the background;
                                  the strategy's training view (TRN-14: resolution)     TRN-07
    Gaussians to render           method.before_render  (theta, or theta_hat / opacity_scale)  TRN-08
    render (backend)              backend.render; clamp the image to [0, 1]             TRN-01
    loss                          L1 + 0.2 (1 - SSIM) against the view's image          TRN-01, MET-08
    gradients                     backend.render_backward; method.after_backward        TRN-01, TRN-08
    densification                 the strategy (refgs.train.strategy): statistics,
                                  densify-and-prune (method.on_densify), opacity reset,
                                  while t < until; compact: budget, pruning      TRN-04..TRN-06, TRN-14
    optimizer step                Adam at the learning rates of t, leaving
                                  method.frozen_rows alone; not at t = T, not for the
                                  tensors replaced by densification (as 3DGS)           TRN-02, TRN-03
    method.after_step             e.g. the flat-minima reinitialisation (FM-06, FM-07)

The trainer reaches the renderer only through ``backend`` (an object with ``render`` /
``render_backward``, chosen by the caller) and the training method only through the hooks of
``refgs.train.hooks.Method`` (the caller passes the method object), so a faster backend, the
flat-minima method or DropGaussian plug in without changing this loop.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, fields

import numpy as np

from ..errors import ConfigError, RefgsError
from ..metrics.psnr import psnr
from ..types import Gaussians, RenderConfig
from .adam import Adam
from .densify import DensifyConfig, DensifyStats, densify_preset
from .hooks import Method
from .loss import FORM_L1_PLUS, LAMBDA_DSSIM, LOSS_FORMS, photometric_loss
from .schedule import SH_MAX_DEGREE, learning_rates, sh_degree_at
from .strategy import CompactConfig, make_strategy

#: Background choices: black (DropGaussian default, ``random_background False``), white
#: (3DGS ``--white_background``), random (3DGS ``--random_background``: a uniform colour per
#: iteration from the run's random stream; evaluation then uses black).  [TRN-07]
BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0), "random": None}
#: Weight of the newest loss in the progress bar's running mean (3DGS ``ema_loss_for_log``).
LOSS_EMA_WEIGHT = 0.4
#: Independent random streams of a run, spawned from its seed in this order (TRN-09).
RNG_STREAMS = ("views", "densify", "method")
DTYPES = {"float64": np.float64, "float32": np.float32}
PARAM_NAMES = Gaussians.FIELDS
#: History curves of integer counts (kept as int through checkpoints).
COUNT_CURVES = ("n_gaussians", "fragments")
#: The method a trainer built without a method object runs (plain 3DGS, DG-02).
PLAIN_METHOD = Method.name


class TrainingDiverged(RefgsError):
    """The loss became NaN or infinite."""


@dataclass(frozen=True)
class TrainConfig:
    """Every setting of a run (written to config.json; TRN-07)."""

    scene: str
    views: int
    iters: int
    seed: int = 0
    images: str = "images_8"
    resolution: float | None = None
    method: str = "3dgs"
    method_params: dict = field(default_factory=dict)
    backend: str = "reference"
    init_points: str = "train-views"
    checkpoint_every: int = 1000
    eval_every: int | None = None
    strict: bool = False
    dtype: str = "float32"
    profile: str = "inria"
    sh_degree: int = SH_MAX_DEGREE
    background: str = "black"
    loss_form: str = FORM_L1_PLUS
    lambda_dssim: float = LAMBDA_DSSIM
    clamp_render: bool = True
    densify_preset: str = "dropgaussian"
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    #: None: the paper's densification (PaperStrategy); else the compact strategy's settings
    #: (TRN-14). Left out of ``to_dict`` when None, so the settings (and their hash) of runs
    #: made before it existed stay what they were.
    compact: CompactConfig | None = None
    holdout: int = 8
    triangulation: str = "tuned"
    lpips: bool = True

    def validate(self, method_names=None) -> "TrainConfig":
        """Check every setting; ConfigError naming the flag.  ``method_names``: the known
        ``--method`` names (refgs.methods.METHOD_NAMES, given by the caller: training does not
        import the methods); None skips that check."""
        def positive(name, v, zero_ok=False):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (0 if zero_ok else 1):
                raise ConfigError(f"--{name.replace('_', '-')}: expected a "
                                  f"{'non-negative' if zero_ok else 'positive'} integer, got {v!r}")
        positive("iters", self.iters)
        positive("views", self.views)
        positive("checkpoint_every", self.checkpoint_every, zero_ok=True)
        if self.eval_every is not None:
            positive("eval_every", self.eval_every, zero_ok=True)
        if not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ConfigError(f"--seed: expected a non-negative integer, got {self.seed!r}")
        if method_names is not None and self.method not in method_names:
            raise ConfigError(f"--method: expected one of {sorted(method_names)}, got {self.method!r}")
        if self.dtype not in DTYPES:
            raise ConfigError(f"--dtype: expected one of {sorted(DTYPES)}, got {self.dtype!r}")
        if self.background not in BACKGROUNDS:
            raise ConfigError(f"--background: expected one of {sorted(BACKGROUNDS)}, got {self.background!r}")
        if self.loss_form not in LOSS_FORMS:
            raise ConfigError(f"--loss-form: expected one of {LOSS_FORMS}, got {self.loss_form!r}")
        if not 0.0 <= self.lambda_dssim <= 1.0:
            raise ConfigError(f"--lambda-dssim: expected a value in [0, 1], got {self.lambda_dssim!r}")
        if not 0 <= self.sh_degree <= SH_MAX_DEGREE:
            raise ConfigError(f"--sh-degree: expected 0..{SH_MAX_DEGREE}, got {self.sh_degree!r}")
        if self.profile not in ("inria", "gsplat"):
            raise ConfigError(f"--profile: expected inria or gsplat, got {self.profile!r}")
        self.densify.validate()
        if self.compact is not None:
            self.compact.validate()
        return self

    @property
    def eval_interval(self) -> int:
        """Test-PSNR interval; default T // 10 (0 = only at the end)."""
        return max(1, self.iters // 10) if self.eval_every is None else int(self.eval_every)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["densify"] = self.densify.to_dict()
        if self.compact is None:
            del d["compact"]
        else:
            d["compact"] = self.compact.to_dict()
        return d

    @staticmethod
    def from_dict(d: dict) -> "TrainConfig":
        names = {f.name for f in fields(TrainConfig)}
        unknown = set(d) - names
        if unknown:
            raise ConfigError(f"config.json: unknown settings {sorted(unknown)}")
        kw = dict(d)
        kw["densify"] = DensifyConfig(**kw.get("densify", {}))
        if kw.get("compact") is not None:
            kw["compact"] = CompactConfig.from_dict(kw["compact"])
        return TrainConfig(**kw)

    @staticmethod
    def with_preset(preset: str = "dropgaussian", densify_overrides: dict | None = None, **kw):
        return TrainConfig(densify_preset=preset,
                           densify=densify_preset(preset, **(densify_overrides or {})), **kw)


@dataclass
class View:
    """A training or test view: name, refgs.Camera, image (H, W, 3) in [0, 1]."""

    name: str
    camera: object
    image: np.ndarray


class Trainer:
    """State and loop of one run (TRN-01..TRN-09).

    cfg          TrainConfig
    train_views, test_views   lists of View
    params       name -> array (refgs.Gaussians fields), copied in ``cfg.dtype``
    extent       scene extent e (refgs.train.schedule.scene_extent)
    backend      the renderer (refgs.train.backend); optional ``adam_update`` / ``ssim_and_grad`` /
                 ``l1_ssim_loss``
    method       the training method's hooks (refgs.train.hooks.Method; the caller builds it,
                 e.g. ``refgs.methods.make_method(cfg.method, cfg.method_params)``); None only
                 for plain 3DGS (``cfg.method == "3dgs"``)

    Everything needed to continue bit-exactly is in ``state_arrays`` / ``state_meta``.
    """

    def __init__(self, cfg: TrainConfig, train_views: list, test_views: list, params: dict,
                 extent: float, backend, method: Method | None = None):
        if method is None:
            if cfg.method != PLAIN_METHOD:
                raise ConfigError(f"--method {cfg.method}: the trainer needs its method object "
                                  "(refgs.methods.make_method(cfg.method, cfg.method_params))")
            method = Method()
        self.cfg = cfg
        self.train_views = list(train_views)
        self.test_views = list(test_views)
        self.params = {k: np.array(params[k], dtype=DTYPES[cfg.dtype]) for k in PARAM_NAMES}
        self.extent = float(extent)
        self.backend = backend
        self.method = method
        self.strategy = make_strategy(cfg.compact)
        self.adam = Adam(self.params, kernel=getattr(self.backend, "adam_update", None))
        self.stats = DensifyStats(len(self.params["means"]))
        self.t = 0
        seeds = np.random.SeedSequence(int(cfg.seed)).spawn(len(RNG_STREAMS))
        self.rngs = {k: np.random.Generator(np.random.PCG64(s)) for k, s in zip(RNG_STREAMS, seeds)}
        self.view_stack: list[int] = []
        #: per-iteration curves (train_*, n_gaussians, fragments: the render's pixel-Gaussian
        #: pairs, TRN-14; seconds) and the test points (test_t, test_psnr; TRN-07)
        self.history = {k: [] for k in ("train_t", "train_loss", "train_psnr", "test_t",
                                        "test_psnr", "n_gaussians", "fragments", "iter_seconds",
                                        "iter_cpu_seconds")}
        self.train_seconds = 0.0
        self.loss_ema = 0.0
        #: the initial point cloud {"points": (M,3), "colors": (M,3)} the run started from, kept in
        #: every checkpoint (TRN-09); set by the caller that made it
        self.init_cloud: dict | None = None
        #: the view and render settings of the iteration in progress (for the method's hooks)
        self.current_view: View | None = None
        self.current_render_config: RenderConfig | None = None
        self.method.setup(self)

    # --- parameters -----------------------------------------------------------------------
    def gaussians(self) -> Gaussians:
        return Gaussians(**{k: self.params[k] for k in PARAM_NAMES})

    @property
    def n(self) -> int:
        return len(self.params["means"])

    def eval_background(self) -> tuple:
        return BACKGROUNDS[self.cfg.background] or BACKGROUNDS["black"]

    # --- one iteration --------------------------------------------------------------------
    def step(self) -> dict:
        """Run iteration t = self.t + 1 (the data flow of the module docstring); returns the
        iteration's loss, training-view PSNR and view name."""
        cfg, method = self.cfg, self.method
        t0, c0 = time.perf_counter(), time.process_time()
        t = self.t + 1
        # scene view -> Gaussians to render (the method's hook: theta, theta_hat, opacity scale)
        view, background = self.next_view()
        view = self.strategy.training_view(self, view, t)
        request = method.before_render(self, t, self.rngs["method"])
        rcfg = RenderConfig(profile=cfg.profile, sh_degree=sh_degree_at(t, cfg.sh_degree),
                            background=background, opacity_scale=request.opacity_scale)
        self.current_view, self.current_render_config = view, rcfg
        # render (backend) -> loss -> gradients of the render, then of the stored parameters
        loss, grads, out, shown = self.loss_and_grads(request.gaussians, view, rcfg, t)
        param_grads = method.after_backward(self, t, request, grads)
        # densification -> optimizer step (not at t = T) -> the method's end of iteration
        replaced = self.densification(t, grads, out, view)
        if t < cfg.iters and len(replaced) < len(PARAM_NAMES):
            lrs = learning_rates(t, cfg.iters, self.extent, self.params["sh"].shape[1])
            self.adam.step(self.params, param_grads, lrs, skip=replaced,
                           frozen_rows=method.frozen_rows(self, t))
        method.after_step(self, t, self.rngs["method"])

        self.t = t
        value = psnr(shown, view.image)
        self.loss_ema = LOSS_EMA_WEIGHT * loss + (1 - LOSS_EMA_WEIGHT) * self.loss_ema
        seconds = time.perf_counter() - t0
        for key, v in (("train_t", t), ("train_loss", loss), ("train_psnr", value),
                       ("n_gaussians", self.n),
                       ("fragments", int(np.sum(out.n_contrib, dtype=np.int64))),
                       ("iter_seconds", seconds),
                       ("iter_cpu_seconds", time.process_time() - c0)):
            self.history[key].append(v)
        self.train_seconds += seconds
        return {"t": t, "loss": loss, "psnr": value, "view": view.name}

    def next_view(self) -> tuple:
        """The training view of this iteration, popped at a random index of the shuffled stack
        (refilled when empty), and the background colour (TRN-07); both from the ``views``
        random stream, in that order."""
        rng = self.rngs["views"]
        if not self.view_stack:
            self.view_stack = list(range(len(self.train_views)))
        view = self.train_views[self.view_stack.pop(int(rng.integers(len(self.view_stack))))]
        background = BACKGROUNDS[self.cfg.background]
        if background is None:
            background = tuple(float(x) for x in rng.random(3))
        return view, background

    def densification(self, t: int, grads, out, view: View) -> set:
        """Adaptive density control of iteration t by the run's strategy (TRN-04..TRN-06,
        TRN-14; refgs.train.strategy); returns the names of the parameter tensors replaced,
        which take no Adam step this iteration (as 3DGS: a replaced tensor has no gradient)."""
        return self.strategy.densification(self, t, grads, out, view)

    def loss_and_grads(self, gaussians: Gaussians, view: View, rcfg: RenderConfig, t: int):
        """Render ``gaussians`` from ``view``, the loss against its image and the backward
        (TRN-01): returns ``(loss, Gradients, render output, clamped image)``.  Methods that need
        a second render in an iteration (the mixed-loss ablation, FM-11) call it with
        ``current_view`` / ``current_render_config``."""
        cfg = self.cfg
        out = self.backend.render(gaussians, view.camera, rcfg)
        image = out.image
        shown = np.clip(image, 0.0, 1.0)
        loss, v_image = photometric_loss(shown if cfg.clamp_render else image, view.image,
                                         cfg.lambda_dssim, cfg.loss_form,
                                         getattr(self.backend, "ssim_and_grad", None),
                                         getattr(self.backend, "l1_ssim_loss", None))
        if not np.isfinite(loss):
            raise TrainingDiverged(f"training diverged at iteration {t}: loss is {loss}")
        if cfg.clamp_render:  # torch.clamp passes the gradient where min <= x <= max
            v_image = v_image * ((image >= 0.0) & (image <= 1.0))
        return loss, self.backend.render_backward(out, v_image), out, shown

    # --- evaluation -----------------------------------------------------------------------
    def render_view(self, view: View, gaussians: Gaussians | None = None) -> np.ndarray:
        """Plain render of the stored parameters (or of ``gaussians``, e.g. perturbed ones for
        the flatness analysis), clamped to [0, 1] (TRN-07)."""
        rcfg = RenderConfig(profile=self.cfg.profile, sh_degree=sh_degree_at(self.t, self.cfg.sh_degree),
                            background=self.eval_background())
        g = self.gaussians() if gaussians is None else gaussians
        return np.clip(self.backend.render(g, view.camera, rcfg).image, 0.0, 1.0)

    def test_psnr(self) -> float:
        """Mean PSNR over the test views (recorded in the history)."""
        value = float(np.mean([psnr(self.render_view(v), v.image) for v in self.test_views]))
        self.history["test_t"].append(self.t)
        self.history["test_psnr"].append(value)
        return value

    # --- checkpoint state -----------------------------------------------------------------
    def state_arrays(self) -> dict:
        out = {f"param/{k}": v for k, v in self.params.items()}
        out.update(self.adam.state_arrays())
        out.update(self.stats.state_arrays())
        out.update({f"history/{k}": np.asarray(v, dtype=np.float64) for k, v in self.history.items()})
        out.update({f"method/{k}": v for k, v in self.method.state_arrays().items()})
        if self.init_cloud is not None:
            out.update({f"init/{k}": np.asarray(v) for k, v in self.init_cloud.items()})
        return out

    def state_meta(self) -> dict:
        from .checkpoint import rng_state
        return {"iteration": self.t, "rng": {k: rng_state(r) for k, r in self.rngs.items()},
                "view_stack": list(self.view_stack), "train_seconds": self.train_seconds,
                "loss_ema": self.loss_ema, "method": self.method.name, "n_gaussians": self.n}

    def load_state(self, arrays: dict, meta: dict) -> None:
        from .checkpoint import rng_from_state
        dt = DTYPES[self.cfg.dtype]
        self.params = {k: np.array(arrays[f"param/{k}"], dtype=dt) for k in PARAM_NAMES}
        self.adam = Adam(self.params, kernel=getattr(self.backend, "adam_update", None))
        self.adam.load_state_arrays(arrays)
        self.stats.load_state_arrays(arrays)
        for k in self.history:
            vals = np.asarray(arrays.get(f"history/{k}", []), np.float64).tolist()
            self.history[k] = [int(v) for v in vals] if k.endswith("_t") or k in COUNT_CURVES else vals
        # a checkpoint from before the fragment count: -1 (not measured) for its iterations
        missing = len(self.history["train_t"]) - len(self.history["fragments"])
        self.history["fragments"] = [-1] * missing + self.history["fragments"]
        self.method.load_state_arrays({k[7:]: v for k, v in arrays.items() if k.startswith("method/")})
        init = {k[5:]: np.asarray(v) for k, v in arrays.items() if k.startswith("init/")}
        self.init_cloud = init or None
        self.t = int(meta["iteration"])
        self.rngs = {k: rng_from_state(meta["rng"][k]) for k in RNG_STREAMS}
        self.view_stack = [int(i) for i in meta["view_stack"]]
        self.train_seconds = float(meta["train_seconds"])
        self.loss_ema = float(meta["loss_ema"])


__all__ = ["TrainConfig", "Trainer", "View", "BACKGROUNDS", "TrainingDiverged", "RNG_STREAMS",
           "DTYPES", "PLAIN_METHOD"]
