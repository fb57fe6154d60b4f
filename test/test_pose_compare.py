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


def nan_poses(path, field: str, at: int = 2) -> None:
    """Five poses, the one at ``at`` with NaN in its position, covariance or orientation."""
    with BagWriter(path) as bag:
        for i in range(5):
            message = fix_to_pose_msg(fix(i), store=bag.store)
            if i == at:
                if field == "position":
                    message.pose.pose.position.x = float("nan")
                elif field == "covariance":
                    message.pose.covariance[:] = np.nan
                elif field == "one_variance":
                    message.pose.covariance[14] = np.inf
                else:
                    message.pose.pose.orientation.w = float("nan")
            bag.write(POSE_TOPIC, message)


@pytest.mark.parametrize("field", ["position", "covariance", "one_variance", "orientation"])
@pytest.mark.parametrize("side", ["reference", "other", "both"])
def test_a_nan_pose_is_never_the_same(tmp_path, capsys, field, side):
    """On main a NaN pose or covariance compared false with the tolerance only where it came
    first: elsewhere ``max`` skipped it, and the command said "the same poses", exit 0."""
    from deepsync.cli import main

    write(tmp_path / "good", [fix(i) for i in range(5)])
    nan_poses(tmp_path / "nan", field)
    reference, other = {"reference": ("nan", "good"), "other": ("good", "nan"), "both": ("nan", "nan")}[side]
    result = compare_poses(tmp_path / reference, tmp_path / other)
    assert result.matched == 5 and result.not_finite == 1 and not result.same()
    assert main(["compare-poses", "--reference", str(tmp_path / reference), "--other", str(tmp_path / other)]) == 1
    out = capsys.readouterr().out
    assert "1 of them hold NaN or inf" in out and "NOT the same poses" in out


def test_poses_in_two_frames_are_refused(tmp_path):
    """Poses published in another frame (another map, an odom frame) were compared metre for
    metre: the frames family's other member."""
    write(tmp_path / "a", [fix(i) for i in range(3)])
    with BagWriter(tmp_path / "b") as bag:
        for i in range(3):
            message = fix_to_pose_msg(fix(i), store=bag.store)
            message.header.frame_id = "odom"
            bag.write(POSE_TOPIC, message)
    with pytest.raises(ValueError, match="the poses of .*a are in frame map, those of .*b in odom"):
        compare_poses(tmp_path / "a", tmp_path / "b")
