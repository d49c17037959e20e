"""The campaign beside the paper: our per-scene means next to the paper's dataset means.

The paper reports means over datasets (LLFF: 8 scenes at 3 views; Mip-NeRF 360: 9 scenes at 12
views), not single scenes, so only the scenes from those datasets have a counterpart: fern (LLFF)
and bonsai (Mip-NeRF 360).  The table gives, per scene and metric, each method's value and the
two differences FM - 3DGS and FM - DropGaussian as "ours / paper" (ours: the mean over the seeds
we have, their counts per method in the row).  Our differences here are differences of means; their paired CIs are in the main table.
"""
from __future__ import annotations

import numpy as np

from .campaign import METRICS, CampaignRun, metric

#: The paper's tables (000_fc0f86eb91ef8558.txt): "Quantitative comparison on the LLFF dataset"
#: (3-view columns) and "Quantitative comparison on MipNeRF360 dataset" (12-view columns), rows
#: 3DGS, DropGaussian, Ours: (PSNR, SSIM, LPIPS).
PAPER = {
    ("fern", 3): ("LLFF 3-view, mean of 8 scenes", {
        "3dgs": (19.22, 0.649, 0.229), "dropgaussian": (20.76, 0.713, 0.200),
        "fm": (20.88, 0.731, 0.184)}),
    ("bonsai", 12): ("Mip-NeRF 360 12-view, mean of 9 scenes", {
        "3dgs": (18.52, 0.523, 0.415), "dropgaussian": (19.74, 0.577, 0.364),
        "fm": (19.50, 0.584, 0.348)}),
}
#: The table's methods, then FM minus each baseline.
METHODS = ("3dgs", "dropgaussian", "fm")
DIFFERENCES = (("fm", "3dgs"), ("fm", "dropgaussian"))
NAMES = {"3dgs": "3DGS", "dropgaussian": "DropGaussian", "fm": "FM"}


def _ours(runs: list[CampaignRun], scene: str, views: int, method: str, key: str):
    vals = [metric(r, key) for r in runs if (r.scene, r.views, r.method) == (scene, views, method)]
    vals = [v for v in vals if v is not None]
    return (float(np.mean(vals)), len(vals)) if vals else (None, 0)


def paper_markdown(runs: list[CampaignRun]) -> str:
    """The table of the module docstring: a row per scene with a counterpart and metric, each
    cell "ours / paper"."""
    head = ["scene", "paper's mean over", "metric", "seeds (ours)", *(NAMES[m] for m in METHODS),
            *(f"{NAMES[a]} − {NAMES[b]}" for a, b in DIFFERENCES)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (scene, views), (dataset, paper) in PAPER.items():
        for i, (key, title, dec) in enumerate(METRICS):
            ours = {m: _ours(runs, scene, views, m, key) for m in METHODS}
            cells = [f"{scene} {views}-view", dataset, title,
                     "/".join(str(ours[m][1]) for m in METHODS)]
            for m in METHODS:
                v = ours[m][0]
                cells.append(f"{'-' if v is None else f'{v:.{dec}f}'} / {paper[m][i]:.{dec}f}")
            for a, b in DIFFERENCES:
                va, vb = ours[a][0], ours[b][0]
                mine = "-" if va is None or vb is None else f"{va - vb:+.{dec}f}"
                cells.append(f"{mine} / {paper[a][i] - paper[b][i]:+.{dec}f}")
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


__all__ = ["PAPER", "paper_markdown"]
