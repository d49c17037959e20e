"""What a grid's runs cost, from their records: per cell the training loop's time, the Gaussians
at T and the peak memory, and the campaign's compute and wall time (FM-15: every number from a
record; a report's ``[report.cost]`` table, refgs.analysis.report).

A record's ``history.json`` holds ``iter_seconds`` (one wall-clock duration per iteration) and its
``config.json`` the time the run ``started`` and every resume (``resumes``: ``from_iteration``,
``time``).  A run's training is therefore a list of *segments*: the first from ``started`` over
iterations [0, from_1), each resume from its ``time`` over [from_k, from_k+1), the last up to the
end; a segment lasts the sum of its iterations' seconds.  The campaign's **wall time** is the
length of the union of every run's segments (the time during which at least one of its runs was
training: two runs side by side count once, the breaks between sessions not at all); its
**compute** is the sum of the training loops.  Both leave out each run's setup (scene loading,
triangulation: seconds) and its final evaluation (test renders and LPIPS: about a minute).
"""
from __future__ import annotations

from datetime import datetime, timedelta
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..runs import CONFIG_FILE, HISTORY_FILE
from .report_tables import ReportRun, head, metric, prose, row
from .tables import read_run_json

#: The timestamp format of ``started`` and of a resume's ``time`` (refgs.runs).
TIME_FORMAT = "%Y-%m-%dT%H:%M:%S%z"
COMPUTE_HEADING = "### What the campaign cost"


def _time(value, where: str) -> datetime:
    try:
        return datetime.strptime(str(value), TIME_FORMAT)
    except ValueError:
        raise ConfigError(f"{where}: {value!r} is not a time like 2026-12-05T10:30:35+0000") from None


def segments(config: dict, history: dict, where: str) -> list[tuple[datetime, datetime]]:
    """The (start, end) of each training segment of one run (module docstring)."""
    secs = history.get("iter_seconds")
    if not isinstance(secs, list) or not secs:
        raise ConfigError(f"{where}/{HISTORY_FILE}: no iter_seconds list")
    secs = np.asarray(secs, np.float64)
    starts = [(_time(config.get("started"), f"{where}/{CONFIG_FILE} started"), 0)]
    for k, res in enumerate(config.get("resumes") or []):
        try:
            frm = int(res["from_iteration"])
        except (KeyError, TypeError, ValueError):
            raise ConfigError(f"{where}/{CONFIG_FILE}: resume {k} has no from_iteration") from None
        starts.append((_time(res.get("time"), f"{where}/{CONFIG_FILE} resume {k}"), frm))
    bounds = [frm for _, frm in starts[1:]] + [secs.size]
    return [(t0, t0 + timedelta(seconds=float(secs[a:b].sum())))
            for (t0, a), b in zip(starts, bounds)]


def loop_seconds(config: dict, history: dict, where: str) -> float:
    """The training loop of one run in seconds: the length of its segments (module docstring)."""
    return sum((b - a).total_seconds() for a, b in segments(config, history, where))


def union_seconds(intervals: list[tuple[datetime, datetime]]) -> float:
    """The length in seconds of the union of (start, end) intervals."""
    total, end = 0.0, None
    for a, b in sorted(intervals):
        if end is None or a > end:
            total += (b - a).total_seconds()
            end = b
        elif b > end:
            total += (b - end).total_seconds()
            end = b
    return total


def cost_markdown(records_dir: str | Path, runs: list[ReportRun], groups, methods,
                  note: str) -> str:
    """The heading, the per-cell table (``groups`` x ``methods``) and the totals of the records
    ``runs``, then ``note``."""
    if not runs:
        return "\n".join([COMPUTE_HEADING, "", "No campaign records yet.", ""])
    lines = head(["scene", "views", "method", "n", "training loop, min (mean; range)",
                  "Gaussians at T (mean)", "peak RSS, GB (max)"])
    all_segments, loop_total = [], 0.0
    for scene, views in groups:
        for method in methods:
            rs = [r for r in runs if (r.scene, r.views, r.method) == (scene, views, method)]
            if not rs:
                continue
            loops = []
            for r in rs:
                folder = Path(records_dir) / r.record
                segs = segments(read_run_json(folder / CONFIG_FILE),
                                read_run_json(folder / HISTORY_FILE), str(folder))
                all_segments += segs
                loops.append(sum((b - a).total_seconds() for a, b in segs) / 60)
            loop_total += sum(loops)
            gaussians = [metric(r, "n_gaussians") for r in rs]
            rss = [metric(r, "peak_rss_gb") for r in rs]
            lines.append(row([
                scene, str(views), method, str(len(rs)),
                f"{np.mean(loops):.1f}; {min(loops):.1f}-{max(loops):.1f}",
                "n/a" if None in gaussians else f"{np.mean(gaussians):,.0f}",
                "n/a" if None in rss else f"{max(rss):.2f}"]))
    first = min(a for a, _ in all_segments)
    last = max(b for _, b in all_segments)
    wall = union_seconds(all_segments) / 3600
    text = (f"{len(runs)} runs; their training loops add up to {loop_total / 60:.1f} h of "
            f"compute; the campaign's wall time (the union of the runs' training intervals: "
            f"two runs side by side count once, breaks between sessions not at all) is "
            f"{wall:.1f} h, between {first:%Y-%m-%d %H:%M} and {last:%Y-%m-%d %H:%M} UTC. {note}")
    return "\n".join([COMPUTE_HEADING, "", prose(text), "", *lines, ""])


__all__ = ["segments", "loop_seconds", "union_seconds", "cost_markdown"]
