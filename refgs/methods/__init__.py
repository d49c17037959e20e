"""Training methods: the paper's flat-minima method (flat_minima) and the DropGaussian baseline."""
from .flat_minima import (CLAMP_MODES, GAMMA, P_PERTURB, REINIT_INTERVAL, REINIT_WINDOW, NoiseShape,
                          clamp_displacement, clipped_fraction, is_reinit_iteration, magnitude_schedule,
                          perturb_probability, reinit_values, sap_offsets)
from .dropgaussian import R_MAX, drop_opacity_scale, drop_rate

__all__ = ["CLAMP_MODES", "GAMMA", "P_PERTURB", "REINIT_INTERVAL", "REINIT_WINDOW", "NoiseShape",
           "clamp_displacement", "clipped_fraction", "is_reinit_iteration", "magnitude_schedule",
           "perturb_probability", "reinit_values", "sap_offsets", "R_MAX", "drop_opacity_scale",
           "drop_rate"]
