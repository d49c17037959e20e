"""Training methods: the paper's flat-minima method and the DropGaussian baseline (DG-02).

    flat_minima.py           the method's ideas, one function per idea (FM-01..FM-08, FM-10)
    dropgaussian.py          DropGaussian's drop rate and opacity compensation (DG-01)
    flat_minima_method.py    the flat-minima method's trainer hooks (refgs/train/hooks.py)
    dropgaussian_method.py   DropGaussian's trainer hook
    registry.py              the one table of ``--method`` names: METHOD_NAMES, make_method,
                             method_params
"""
from .flat_minima import (CLAMP_MODES, GAMMA, P_PERTURB, REINIT_INTERVAL, REINIT_WINDOW, NoiseShape,
                          clamp_displacement, clipped_fraction, is_reinit_iteration, magnitude_schedule,
                          perturb_probability, reinit_values, sap_offsets)
from .dropgaussian import R_MAX, drop_opacity_scale, drop_rate
from .registry import METHOD_NAMES, make_method, method_params

__all__ = ["CLAMP_MODES", "GAMMA", "P_PERTURB", "REINIT_INTERVAL", "REINIT_WINDOW", "NoiseShape",
           "clamp_displacement", "clipped_fraction", "is_reinit_iteration", "magnitude_schedule",
           "perturb_probability", "reinit_values", "sap_offsets", "R_MAX", "drop_opacity_scale",
           "drop_rate", "METHOD_NAMES", "make_method", "method_params"]
