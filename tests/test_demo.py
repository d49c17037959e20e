"""`refgs demo` (refgs.analysis.demo): the protocol's schedule compressed, the two runs' settings
and the comparison picture; the end-to-end run is tests/test_train_fern.py::test_demo_command."""
from __future__ import annotations

import pytest

from refgs.analysis import demo
from refgs.errors import ConfigError


def test_schedule_is_the_protocol_compressed():
    assert demo.demo_schedule(demo.PROTOCOL_ITERS) == demo.PROTOCOL_SCHEDULE
    assert demo.demo_schedule(1000) == {"start": 50, "interval": 10, "opacity_reset_interval": 300,
                                        "reinit_interval": 100, "reinit_window": 10,
                                        "eval_every": 50}
    assert min(demo.demo_schedule(6).values()) == 1          # never 0, even for a 6-iteration test


def test_configs_differ_only_in_the_method():
    a = demo.demo_config("3dgs", "scene", 1000, "fast", 0).to_dict()
    b = demo.demo_config("fm", "scene", 1000, "fast", 0).to_dict()
    assert {k for k in a if a[k] != b[k]} == {"method", "method_params"}
    assert b["method_params"]["reinit_interval"] == 100 and b["method_params"]["reinit_window"] == 10
    assert a["densify"]["start"] == 50 and a["densify"]["interval"] == 10
    # test points every T/20, before each multiple (refgs.runs.is_test_point, TRN-07)
    assert a["views"] == demo.DEMO_VIEWS and a["eval_every"] == 50 and a["checkpoint_every"] == 0


def test_unknown_method_is_one_line():
    with pytest.raises(ConfigError, match="demo method: expected one of"):
        demo.demo_config("sam", "scene", 10, "fast", 0)
