"""Training: the photometric loss (loss.py) and, added by other modules, the optimiser and loop."""
