"""The live-vs-offline check: two bags' poses matched by stamp (deepsync.eval.compare)."""

import numpy as np
import pytest

from deepsync.bag import POSE_TOPIC, BagWriter, fix_to_pose_msg
from deepsync.eval.compare import compare_poses
from deepsync.types import Fix

STAMP_NS = 1_767_225_600 * 10**9


def fix(i: int, shift_m: float = 0.0, sigma_m: float = 10.0) -> Fix:
    covariance = np.diag([sigma_m**2 / 2, sigma_m**2 / 2, 1e6])
    return Fix(STAMP_NS + i * 100_000_000, (100.0 + i + shift_m, -50.0 + 2 * i, 0.0), covariance, ("A", "B", "C"))


def write(path, fixes) -> None:
    with BagWriter(path) as bag:
        for f in fixes:
            bag.write(POSE_TOPIC, fix_to_pose_msg(f, store=bag.store))


def test_the_same_poses_are_the_same(tmp_path):
    write(tmp_path / "a", [fix(i) for i in range(5)])
    write(tmp_path / "b", [fix(i) for i in range(5)])
    result = compare_poses(tmp_path / "a", tmp_path / "b")
    assert (result.matched, result.only_reference, result.only_other) == (5, 0, 0)
    assert result.max_difference_m == 0 and result.max_sigma_ratio == 1
    assert result.same()


@pytest.mark.parametrize("other, counts, why", [
    ([fix(i) for i in range(4)], (4, 1, 0), "a pose dropped"),
    ([fix(i, shift_m=0.5 if i == 2 else 0.0) for i in range(5)], (5, 0, 0), "a pose moved by 0.5 m"),
    ([fix(i, sigma_m=20.0 if i == 3 else 10.0) for i in range(5)], (5, 0, 0), "a sigma doubled"),
])
def test_a_difference_is_found(tmp_path, other, counts, why):
    write(tmp_path / "a", [fix(i) for i in range(5)])
    write(tmp_path / "b", other)
    result = compare_poses(tmp_path / "a", tmp_path / "b")
    assert (result.matched, result.only_reference, result.only_other) == counts
    assert not result.same(), why


def test_positions_are_compared_in_metres(tmp_path):
    write(tmp_path / "a", [fix(i) for i in range(3)])
    write(tmp_path / "b", [fix(i, shift_m=0.05) for i in range(3)])
    result = compare_poses(tmp_path / "a", tmp_path / "b")
    assert result.max_difference_m == pytest.approx(0.05)
    assert result.same(tolerance_m=0.1) and not result.same(tolerance_m=0.01)


def test_the_command_says_same_or_not_by_its_exit_status(tmp_path, capsys):
    from deepsync.cli import main

    write(tmp_path / "a", [fix(i) for i in range(3)])
    write(tmp_path / "b", [fix(i, shift_m=0.5) for i in range(3)])
    assert main(["compare-poses", "--reference", str(tmp_path / "a"), "--other", str(tmp_path / "a")]) == 0
    assert "the same poses" in capsys.readouterr().out
    assert main(["compare-poses", "--reference", str(tmp_path / "a"), "--other", str(tmp_path / "b")]) == 1
    assert "NOT the same" in capsys.readouterr().out
    assert main(["compare-poses", "--reference", str(tmp_path / "a"), "--other", str(tmp_path / "b"),
                 "--tolerance", "1"]) == 0
