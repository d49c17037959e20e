"""The sparse-view split (DAT-10): llffhold=8 test views, linspace + banker's round train views."""
from __future__ import annotations

import random

import pytest
from conftest import data_root

from refgs.data.split import LLFF_HOLD, split_views
from refgs.errors import ConfigError

DATA = data_root()  # $REFGS_DATA or <repo>/../shared/data

# fern: 20 images IMG_4026 .. IMG_4045 (ranks 0..19).  Test ranks 0, 8, 16.  The 17 other ranks
# are 1-7, 9-15, 17-19; linspace(0, 16, n) picks positions in that list:
#   n=3: 0, 8, 16                      -> ranks 1, 10, 19
#   n=6: 0, 3.2, 6.4, 9.6, 12.8, 16    -> 0, 3, 6, 10, 13, 16 -> ranks 1, 4, 7, 12, 15, 19
#   n=9: 0, 2, 4, ..., 16              -> ranks 1, 3, 5, 7, 10, 12, 14, 17, 19
FERN = [f"IMG_{4026 + k}.png" for k in range(20)]
FERN_TEST = ["IMG_4026.png", "IMG_4034.png", "IMG_4042.png"]
FERN_TRAIN = {
    3: ["IMG_4027.png", "IMG_4036.png", "IMG_4045.png"],
    6: ["IMG_4027.png", "IMG_4030.png", "IMG_4033.png", "IMG_4038.png", "IMG_4041.png",
        "IMG_4045.png"],
    9: ["IMG_4027.png", "IMG_4029.png", "IMG_4031.png", "IMG_4033.png", "IMG_4036.png",
        "IMG_4038.png", "IMG_4040.png", "IMG_4043.png", "IMG_4045.png"],
}


@pytest.mark.parametrize("n", [3, 6, 9])
def test_fern_split_by_hand(n):
    train, test = split_views(FERN, n)
    assert [FERN[i] for i in train] == FERN_TRAIN[n]
    assert [FERN[i] for i in test] == FERN_TEST


def test_fern_files_on_disk_have_these_names():
    folder = DATA / "fern" / "images_8"
    if not folder.is_dir():
        pytest.skip("shared data not available")
    assert sorted(p.name for p in folder.iterdir()) == FERN


def test_order_of_input_does_not_matter():
    shuffled = FERN[:]
    random.Random(3).shuffle(shuffled)
    train, test = split_views(shuffled, 6)
    assert [shuffled[i] for i in train] == FERN_TRAIN[6]
    assert [shuffled[i] for i in test] == FERN_TEST


def test_bankers_rounding():
    # 7 names: test rank 0, six others (ranks 1..6); linspace(0, 5, 3) = 0, 2.5, 5 and Python
    # round(2.5) = 2 (half to even), so ranks 1, 3, 6 (round-half-up would give 1, 4, 6).
    names = [f"v{k}" for k in range(7)]
    train, test = split_views(names, 3)
    assert train == [1, 3, 6]
    assert test == [0]


def test_all_non_test_views_and_none():
    train, test = split_views(FERN, 17)
    assert sorted(train + test) == list(range(20))
    assert split_views(FERN, None) == (train, test)
    assert LLFF_HOLD == 8


def test_sorted_order_is_python_string_order():
    names = ["10.jpg", "2.jpg", "1.jpg", "3.jpg", "11.jpg"]  # sorted: 1, 10, 11, 2, 3
    train, test = split_views(names, None)
    assert [names[i] for i in test] == ["1.jpg"]
    assert [names[i] for i in train] == ["10.jpg", "11.jpg", "2.jpg", "3.jpg"]


@pytest.mark.parametrize("n", [18, 0, -1, 2.5, True, "3"])
def test_bad_view_count_names_the_flag(n):
    with pytest.raises(ConfigError, match="--views"):
        split_views(FERN, n)


def test_duplicate_names_rejected():
    with pytest.raises(ConfigError):
        split_views(["a", "a", "b"], 1)
