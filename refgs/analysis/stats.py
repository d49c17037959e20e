"""Paired statistics of ``refgs table --baseline``: methods against a baseline over seeds (FM-16).

Runs are compared within a *condition*: the same scene, number of views and every training
setting except the method (with its parameters) and the seed.  Settings that do not change the
trained model or its test metrics (``BOOKKEEPING_SETTINGS``) are left out.  Within a condition a
method's run and the baseline's run with the same seed form a pair; per metric the paired
difference is ``d_s = method_s - baseline_s`` in the metric's own units (so a negative LPIPS
difference is an improvement).  For the ``n`` pairs of one (condition, method, metric):

- ``mean_diff`` = mean of ``d``; ``ci95`` the Student-t interval of the mean,
  ``mean +- t_{0.975, n-1} s / sqrt(n)`` (``scipy.stats.ttest_1samp(d).confidence_interval``);
- ``p_value`` of the paired t-test (``ttest_1samp(d, 0)``, identical to ``ttest_rel``), and with
  ``n >= WILCOXON_MIN_PAIRS`` the Wilcoxon signed-rank p (``scipy.stats.wilcoxon``) beside it;
- ``runs_needed``: the smallest number of seeds ``n'`` at which a two-sided paired t-test at
  ``ALPHA`` detects the observed mean difference with probability ``POWER``, given the observed
  spread: effect size ``delta = |mean| / s``, power ``P(|T| > t_{1-alpha/2, n'-1})`` with
  ``T ~ nct(n'-1, delta sqrt(n'))`` (``scipy.stats.nct``), iterated over ``n' = 2, 3, ...``.

One pair gives a mean but no interval, test or power (``NO_INTERVAL``).  The pooled comparison
over scenes takes, per (views, settings, method, metric), the per-scene mean differences and
gives their mean and a Student-t interval over scenes (two scenes at least).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from scipy import stats

from ..errors import ConfigError

#: Two-sided significance level and the confidence of the intervals (1 - ALPHA): the usual 5 %.
ALPHA = 0.05
CONFIDENCE = 1.0 - ALPHA
#: Power at which ``runs_needed`` is computed: the conventional 80 % (Cohen, Statistical Power
#: Analysis for the Behavioral Sciences, 1988).
POWER = 0.80
#: Pairs from which the Wilcoxon signed-rank p is reported: with n pairs its exact two-sided p is
#: at least 2 / 2^n, which is 0.0625 > ALPHA at n = 5 and 0.031 at n = 6.
WILCOXON_MIN_PAIRS = 6
#: Largest number of seeds ``runs_needed`` searches (our choice: beyond it a seed study is no
#: plan); a larger need is reported as null with ``MORE_THAN_MAX``.
MAX_RUNS_NEEDED = 10_000
#: Candidate numbers of seeds evaluated per step of the search (vectorised scipy calls).
POWER_BLOCK = 128
#: config.json settings that are keyed on their own (scene by its folder name) and so not part of
#: the condition's other settings.
KEYED_SETTINGS = ("scene", "views", "method", "method_params", "seed")
#: Settings that change neither the trained model nor its test metrics: checkpoint interval,
#: test-PSNR logging interval, the strictness of the image/model matching, whether LPIPS is
#: computed (its absence shows as a null metric).
BOOKKEEPING_SETTINGS = ("checkpoint_every", "eval_every", "strict", "lpips")

NO_INTERVAL = "n = 1: no interval"
ZERO_SPREAD = "zero spread: no interval or test"
NO_EFFECT = "mean difference 0: no runs-needed"
MORE_THAN_MAX = f"more than {MAX_RUNS_NEEDED} runs needed"
#: The scene name of the pooled (over scenes) comparisons.
ALL_SCENES = "all"


# --- conditions ------------------------------------------------------------------------------------
def setup_of(settings: dict) -> dict:
    """The settings of a run other than the keyed and the bookkeeping ones, nested dicts
    flattened to ``outer.inner`` keys (e.g. ``densify.start``)."""
    out = {}
    for k, v in settings.items():
        if k in KEYED_SETTINGS or k in BOOKKEEPING_SETTINGS:
            continue
        if isinstance(v, dict):
            out.update({f"{k}.{kk}": vv for kk, vv in v.items()})
        else:
            out[k] = v
    return out


def setup_labels(runs: list[dict]) -> list[str]:
    """Per run, the settings (``run["setup"]``) in which the given runs differ, as
    ``"iters=3000,dtype=float32"``; ``""`` for every run when they all agree."""
    setups = [r.get("setup") or {} for r in runs]
    keys = sorted({k for s in setups for k in s})
    differ = [k for k in keys if len({json.dumps(s.get(k), sort_keys=True) for s in setups}) > 1]
    return [",".join(f"{k}={s.get(k)}" for k in differ) for s in setups]


def with_setup(scene: str, setup: str) -> str:
    """Scene name with the condition's differing settings: ``fern`` or ``fern (iters=3000)``."""
    return f"{scene} ({setup})" if setup else scene


def conditions(runs: list[dict]) -> list[tuple]:
    """Per run its (scene with settings, views) condition; ConfigError naming both runs when two
    runs share condition, method label and seed."""
    keys = [(with_setup(r["scene"], s), r["views"]) for r, s in zip(runs, setup_labels(runs))]
    seen = {}
    for r, k in zip(runs, keys):
        full = (*k, r["label"], r["seed"])
        if full in seen:
            raise ConfigError(f"{r['run']}: same scene, views, method and seed as {seen[full]} "
                              "(and no other setting differs)")
        seen[full] = r["run"]
    return keys


# --- the statistics ---------------------------------------------------------------------------------
def power(n, effect_size: float) -> np.ndarray:
    """Power of the two-sided one-sample (paired) t-test at ``ALPHA`` with ``n`` pairs (array)
    for a true mean of ``effect_size`` standard deviations (noncentral t, ``scipy.stats.nct``)."""
    n = np.asarray(n, np.float64)
    df = n - 1.0
    crit = stats.t.ppf(1.0 - ALPHA / 2.0, df)
    nc = abs(effect_size) * np.sqrt(n)
    return stats.nct.sf(crit, df, nc) + stats.nct.cdf(-crit, df, nc)


def runs_needed(mean_diff: float, sd_diff: float) -> int | None:
    """Smallest number of seeds (>= 2) at which the paired t-test detects ``mean_diff`` with
    ``POWER`` given the spread ``sd_diff``; None for a zero mean, a zero spread or beyond
    ``MAX_RUNS_NEEDED``."""
    if mean_diff == 0.0 or not sd_diff > 0.0:
        return None
    effect = abs(mean_diff) / sd_diff
    for start in range(2, MAX_RUNS_NEEDED + 1, POWER_BLOCK):
        ns = np.arange(start, min(start + POWER_BLOCK, MAX_RUNS_NEEDED + 1))
        hit = np.flatnonzero(power(ns, effect) >= POWER)
        if hit.size:
            return int(ns[hit[0]])
    return None


def paired_stats(diffs) -> dict:
    """n, mean_diff, sd_diff, ci95, p_value, wilcoxon_p, runs_needed and a note for the paired
    differences ``diffs`` (n >= 1); the statistics that one pair or a zero spread cannot give
    are None and the note says why."""
    d = np.asarray(diffs, np.float64)
    n = int(d.size)
    out = {"n": n, "mean_diff": float(d.mean()), "sd_diff": None, "ci95": None, "p_value": None,
           "wilcoxon_p": None, "runs_needed": None, "note": ""}
    if n < 2:
        out["note"] = NO_INTERVAL
        return out
    sd = float(d.std(ddof=1))
    out["sd_diff"] = sd
    if not sd > 0.0:
        out["note"] = ZERO_SPREAD
        return out
    res = stats.ttest_1samp(d, 0.0)
    ci = res.confidence_interval(confidence_level=CONFIDENCE)
    out["ci95"] = [float(ci.low), float(ci.high)]
    out["p_value"] = float(res.pvalue)
    if n >= WILCOXON_MIN_PAIRS:
        out["wilcoxon_p"] = float(stats.wilcoxon(d).pvalue)
    out["runs_needed"] = runs_needed(out["mean_diff"], sd)
    if out["runs_needed"] is None:
        out["note"] = NO_EFFECT if out["mean_diff"] == 0.0 else MORE_THAN_MAX
    return out


def excludes_zero(ci) -> bool:
    """Whether a [lo, hi] interval lies entirely above or below 0 (False for None)."""
    return ci is not None and (ci[0] > 0.0 or ci[1] < 0.0)


# --- comparisons ------------------------------------------------------------------------------------
def _seed_order(seed):
    """Sort key: numeric seeds in numeric order, anything else after them by its text."""
    return (0, seed, "") if isinstance(seed, (int, float)) else (1, 0, str(seed))


def _seeds(by_seed: dict) -> str:
    return ", ".join(str(s) for s in sorted(by_seed, key=_seed_order))


def metric_value(run: dict, metric: str):
    """A metric of a run as a float, None where the run has none; ConfigError if not finite."""
    v = run["metrics"].get(metric)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{Path(run['run']) / 'metrics.json'}: {metric} = {v!r}, expected a "
                          "finite number or null")
    return float(v)


def compare(runs: list[dict], metrics, baseline: str) -> dict:
    """Every method against ``baseline`` within each condition, per metric.

    ``runs``: dicts with run, scene, views, label, seed, metrics and setup (``tables.load_run``).
    Returns {"comparisons": [...], "details": [...], "pooled": [...], "unpaired": [...]}:
    ``comparisons`` one dict per (condition, method, metric) with at least one pair, keys scene,
    views, method, baseline, metric, n_pairs, mean_diff, ci95, p_value, runs_needed;
    ``details`` the same identifying keys plus seeds, sd_diff, wilcoxon_p, note, in the same
    order; ``pooled`` the comparisons over scenes; ``unpaired`` what could not be paired and why.
    """
    keys = conditions(runs)
    groups: dict = {}
    for r, k in zip(runs, keys):
        groups.setdefault(k, {}).setdefault(r["label"], {})[r["seed"]] = r
    out = {"comparisons": [], "details": [], "pooled": [], "unpaired": []}
    for (scene, views), by_label in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1] or 0)):
        base = by_label.get(baseline)
        for label in sorted(by_label):
            if label == baseline:
                continue
            ident = {"scene": scene, "views": views, "method": label, "baseline": baseline}
            if base is None:
                out["unpaired"].append({**ident, "metrics": list(metrics),
                                        "reason": f"no {baseline} run with this scene, views and settings"})
                continue
            seeds = sorted(set(by_label[label]) & set(base), key=_seed_order)
            missing = []
            for m in metrics:
                pairs = [(s, metric_value(by_label[label][s], m), metric_value(base[s], m)) for s in seeds]
                pairs = [p for p in pairs if p[1] is not None and p[2] is not None]
                if not pairs:
                    missing.append(m)
                    continue
                st = paired_stats([a - b for _, a, b in pairs])
                out["comparisons"].append({**ident, "metric": m, "n_pairs": st["n"],
                                           "mean_diff": st["mean_diff"], "ci95": st["ci95"],
                                           "p_value": st["p_value"], "runs_needed": st["runs_needed"]})
                out["details"].append({**ident, "metric": m, "seeds": [p[0] for p in pairs],
                                       "sd_diff": st["sd_diff"], "wilcoxon_p": st["wilcoxon_p"],
                                       "note": st["note"]})
            if missing:
                reason = (f"no seed in common ({label} seeds {_seeds(by_label[label])}, "
                          f"{baseline} seeds {_seeds(base)})" if not seeds
                          else "the metric is missing from the paired runs' metrics.json")
                out["unpaired"].append({**ident, "metrics": missing, "reason": reason})
    out["pooled"] = pool(out["comparisons"], runs, keys)
    return out


def pool(comparisons: list[dict], runs: list[dict], keys: list[tuple]) -> list[dict]:
    """The comparisons over scenes: per (views, settings, method, baseline, metric) present at
    two scenes or more, the per-scene mean differences, their mean, a Student-t CI over scenes
    and the one-sample t-test p."""
    setup_of_scene = {k[0]: (r["scene"], s) for r, k, s in zip(runs, keys, setup_labels(runs))}
    groups: dict = {}
    for c in comparisons:
        scene, setup = setup_of_scene[c["scene"]]
        key = (c["views"], setup, c["method"], c["baseline"], c["metric"])
        groups.setdefault(key, []).append((scene, c["mean_diff"]))
    pooled = []
    for (views, setup, method, baseline, metric), items in groups.items():
        if len(items) < 2:
            continue
        st = paired_stats([d for _, d in items])
        pooled.append({"scene": with_setup(ALL_SCENES, setup), "views": views, "method": method,
                       "baseline": baseline, "metric": metric, "n_scenes": st["n"],
                       "scenes": [s for s, _ in items], "per_scene_diffs": [d for _, d in items],
                       "mean_diff": st["mean_diff"], "ci95": st["ci95"], "p_value": st["p_value"],
                       "note": st["note"]})
    return pooled


__all__ = ["ALPHA", "CONFIDENCE", "POWER", "WILCOXON_MIN_PAIRS", "MAX_RUNS_NEEDED", "NO_INTERVAL",
           "ALL_SCENES", "BOOKKEEPING_SETTINGS", "setup_of", "setup_labels", "with_setup",
           "conditions", "metric_value", "power", "runs_needed", "paired_stats", "excludes_zero",
           "compare", "pool"]
