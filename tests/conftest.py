"""Shared pytest configuration: hypothesis profiles and small fixtures for the renderer tests.

Hypothesis profiles (select with the environment variable ``HYPOTHESIS_PROFILE``; default ``ci``):

``ci``       derandomized (the same examples on every run and machine), no deadline, no example
             database, a modest number of examples per property.  This is what the default
             ``pytest`` run uses; the whole renderer suite stays within a few minutes on 2 cores.
``release``  randomized, many examples per property: run before a release or after touching a
             gradient (``HYPOTHESIS_PROFILE=release pytest tests/``).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

#: Examples per hypothesis property in the default (ci) run.  Individual tests may lower this
#: further with ``@settings(max_examples=...)`` when one example is expensive.
CI_MAX_EXAMPLES = 15
#: Examples per property in the release profile.
RELEASE_MAX_EXAMPLES = 300

# Scenes are filtered by the threshold-margin rule of tests/strategies.py (``assume``); a
# rejected draw is expected, not a sign of a bad strategy, and one example can take a second.
_SUPPRESSED = [HealthCheck.too_slow, HealthCheck.filter_too_much, HealthCheck.data_too_large]

settings.register_profile(
    "ci", deadline=None, derandomize=True, database=None, max_examples=CI_MAX_EXAMPLES,
    suppress_health_check=_SUPPRESSED, print_blob=True)
settings.register_profile(
    "release", deadline=None, max_examples=RELEASE_MAX_EXAMPLES,
    suppress_health_check=_SUPPRESSED, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

#: Repository root (tests/ lives directly under it).
REPO_ROOT = Path(__file__).resolve().parents[1]


def data_root() -> Path:
    """The shared data folder: $REFGS_DATA if set, else ``<repo>/../shared/data`` (common.md)."""
    env = os.environ.get("REFGS_DATA")
    return Path(env) if env else REPO_ROOT / ".." / "shared" / "data"


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh seeded generator per test (house rule: explicit, seeded randomness)."""
    return np.random.default_rng(20240607)


@pytest.fixture
def shared_data() -> Path:
    """Path of the shared real-scene data; the test is skipped when it is absent."""
    root = data_root()
    if not root.is_dir():
        pytest.skip(f"shared data not found at {root} (set REFGS_DATA)")
    return root


@pytest.fixture(params=["inria", "gsplat"])
def profile_name(request) -> str:
    """Both rasterizer profiles (PRF-*)."""
    return request.param
