"""The training methods by name: the one table behind ``--method`` and ``--fm`` (clause DG-02).

    METHOD_NAMES                    the names ``--method`` accepts
    make_method(name, params)       the method object the trainer runs (refgs.train.hooks.Method),
                                    from the parameters recorded in config.json
    method_params(name, given, fm)  every parameter of the chosen method with its value, from the
                                    options the user gave (what config.json records)

Recorded parameters (``TrainConfig.method_params``): the FlatMinimaConfig fields (FM-01..FM-11)
when the flat-minima method runs (``--method fm`` or ``--fm``), ``r_max`` (DG-01) for
``--method dropgaussian``, and ``fm: True`` when ``--fm`` was given.
"""
from __future__ import annotations

from dataclasses import fields

from ..errors import ConfigError
from ..train.hooks import Method
from .dropgaussian import R_MAX
from .dropgaussian_method import DropGaussianMethod
from .flat_minima_method import FlatMinimaConfig, FlatMinimaMethod

#: --method name -> build(fm_config, r_max, plug_in), ``plug_in`` = ``--fm``: the flat-minima
#: method added to the named one (on plain 3DGS it is the method itself).  [DG-02]
METHODS = {
    "3dgs": lambda fm_config, r_max, plug_in: FlatMinimaMethod(fm_config) if plug_in else Method(),
    "dropgaussian": lambda fm_config, r_max, plug_in: (
        FlatMinimaMethod(fm_config, dropgaussian=True, r_max=r_max) if plug_in
        else DropGaussianMethod(r_max)),
    "fm": lambda fm_config, r_max, plug_in: FlatMinimaMethod(fm_config),
}
METHOD_NAMES = tuple(sorted(METHODS))
#: The flat-minima parameters (``--fm-*`` options), by their recorded names.
FM_PARAMS = tuple(f.name for f in fields(FlatMinimaConfig))
#: DropGaussian's parameter (``--drop-r-max``) and the plug-in flag (``--fm``), recorded names.
DROP_PARAM = "r_max"
PLUG_IN_PARAM = "fm"


def check_method_name(name: str) -> None:
    """ConfigError naming --method unless ``name`` is in METHOD_NAMES."""
    if name not in METHODS:
        raise ConfigError(f"--method: expected one of {sorted(METHOD_NAMES)}, got {name!r}")


def make_method(name: str, params: dict | None = None) -> Method:
    """The method object of ``--method name`` with the recorded parameters ``params``
    (TrainConfig.method_params; None or {} = the defaults).  ConfigError naming --method for an
    unknown name, naming the parameters for unknown keys."""
    check_method_name(name)
    params = dict(params or {})
    plug_in = bool(params.pop(PLUG_IN_PARAM, False))
    r_max = params.pop(DROP_PARAM, R_MAX)
    unknown = set(params) - set(FM_PARAMS)
    if unknown:
        raise ConfigError(f"method parameters: unknown {sorted(unknown)}; expected some of "
                          f"{list(FM_PARAMS) + [DROP_PARAM, PLUG_IN_PARAM]}")
    return METHODS[name](FlatMinimaConfig(**params), r_max, plug_in)


def method_params(name: str, given: dict, fm: bool = False) -> dict:
    """Every parameter of ``--method name`` (with ``--fm`` when ``fm``) with its value: the
    options the user gave (``given``: recorded name -> value, e.g. {"gamma": 1.0}; None values
    count as not given) over the defaults.  This is what config.json records and what
    ``make_method`` takes (DG-02).  ConfigError naming the option when it does not apply."""
    check_method_name(name)
    given = {k: v for k, v in given.items() if v is not None}
    unknown = set(given) - set(FM_PARAMS) - {DROP_PARAM}
    if unknown:
        raise ConfigError(f"method options: unknown {sorted(unknown)}; expected some of "
                          f"{list(FM_PARAMS) + [DROP_PARAM]}")
    if not (name == "fm" or fm) and any(k != DROP_PARAM for k in given):
        raise ConfigError("--fm-*: flat-minima options need --method fm or --fm")
    if name != "dropgaussian" and DROP_PARAM in given:
        raise ConfigError("--drop-r-max: only with --method dropgaussian")
    recorded = dict(make_method(name, dict(given, **{PLUG_IN_PARAM: fm})).params_dict())
    if fm:
        recorded[PLUG_IN_PARAM] = True
    return recorded


__all__ = ["METHOD_NAMES", "METHODS", "make_method", "method_params", "check_method_name",
           "FM_PARAMS"]
