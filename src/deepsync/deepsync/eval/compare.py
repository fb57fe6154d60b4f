"""Do two bags hold the same poses? The check that a live run matches the offline replay.

``ros2 bag play bags/X --clock`` into the nodes, recorded with ``ros2 bag record
/deepsync/pose``, should publish what ``deepsync replay`` writes for the same bag: the same
stages run on the same chunks. Poses are matched by header stamp (the ADC time of their stack,
identical in both), not by log time (a recorder logs arrival time). They differ by rounding
only: the nodes hand windows and co-sited pair coefficients to the next stage as float32
messages, replay keeps the pair coefficients in float64, which moves an arrival by ~1e-4
samples, a position by millimetres. Poses missing on one side mean dropped messages (a node
that fell behind on best-effort ADC data) or a stage that saw a different stream.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deepsync.bag import POSE_TOPIC, BagReader, position_from_pose_msg, stamp_to_ns
from deepsync.bag.convert import POSE_WITH_COVARIANCE_STAMPED

DEFAULT_TOLERANCE_M = 0.1
"""Largest position difference still called "the same pose": far above float32 rounding (mm),
far below the fixes' own sigmas (metres to tens of metres)."""


@dataclass(frozen=True)
class PoseComparison:
    """How the poses of ``other`` match those of ``reference`` (matched by header stamp)."""

    matched: int
    only_reference: int  # stamps with a pose in the reference only
    only_other: int
    max_difference_m: float  # largest 3-D position difference over the matched poses (NaN: none)
    median_difference_m: float
    max_sigma_ratio: float  # largest ratio of the two poses' horizontal sigmas, >= 1 (NaN: none)
    not_finite: int = 0  # matched stamps where either pose holds NaN or inf (position, orientation, covariance)

    def same(self, tolerance_m: float = DEFAULT_TOLERANCE_M) -> bool:
        """Every pose on both sides, finite, within ``tolerance_m``, sigmas within 1 % (a NaN
        compares false with everything, so it is counted, not compared)."""
        return (self.matched > 0 and self.only_reference == 0 and self.only_other == 0 and self.not_finite == 0
                and self.max_difference_m <= tolerance_m and self.max_sigma_ratio <= 1.01)


def _poses(bag: str | Path, topic: str) -> tuple[dict[int, tuple[np.ndarray, float]], set[str]]:
    """Header stamp -> (position, horizontal sigma) of every pose on ``topic``, and the frames
    they are in; a pose holding NaN or inf anywhere (orientation and covariance too) has NaN for
    both."""
    poses, frames = {}, set()
    with BagReader(bag) as reader:
        kind = reader.topics.get(topic)
        if kind is not None and kind != POSE_WITH_COVARIANCE_STAMPED:
            raise ValueError(f"{bag}: {topic} holds {kind}, not {POSE_WITH_COVARIANCE_STAMPED}: "
                             "only poses with a covariance are compared")
        for item in reader.messages([topic]):
            covariance = np.asarray(item.message.pose.covariance, dtype=np.float64).reshape(6, 6)
            position = np.array(position_from_pose_msg(item.message))
            q = item.message.pose.pose.orientation
            if not (np.isfinite(covariance).all() and np.isfinite(position).all()
                    and np.isfinite([q.x, q.y, q.z, q.w]).all()):
                position, covariance = np.full(3, math.nan), np.full((6, 6), math.nan)
            finite = np.isfinite(covariance).all()
            sigma = math.sqrt(max(covariance[0, 0] + covariance[1, 1], 0.0)) if finite else math.nan
            poses[stamp_to_ns(item.message.header.stamp)] = (position, sigma)
            frames.add(item.message.header.frame_id)
    return poses, frames


def compare_poses(reference: str | Path, other: str | Path, topic: str = POSE_TOPIC) -> PoseComparison:
    """Compare the ``PoseWithCovarianceStamped`` messages of ``topic`` in two bags; ValueError
    when their poses are in different frames (positions in two frames compare as nonsense)."""
    (ours, our_frames), (theirs, their_frames) = _poses(reference, topic), _poses(other, topic)
    if our_frames and their_frames and our_frames != their_frames:
        raise ValueError(f"{topic}: the poses of {reference} are in frame {', '.join(sorted(our_frames))}, those of "
                         f"{other} in {', '.join(sorted(their_frames))}: positions in two frames cannot be compared")
    common = sorted(ours.keys() & theirs.keys())
    finite = [t for t in common if math.isfinite(ours[t][1]) and math.isfinite(theirs[t][1])]
    differences = [float(np.linalg.norm(ours[t][0] - theirs[t][0])) for t in finite]
    ratios = [max(ours[t][1], theirs[t][1]) / min(ours[t][1], theirs[t][1]) if min(ours[t][1], theirs[t][1]) > 0
              else math.inf for t in finite]
    nan = math.nan
    return PoseComparison(
        matched=len(common),
        only_reference=len(ours.keys() - theirs.keys()),
        only_other=len(theirs.keys() - ours.keys()),
        max_difference_m=max(differences, default=nan),
        median_difference_m=float(np.median(differences)) if differences else nan,
        max_sigma_ratio=max(ratios, default=nan),
        not_finite=len(common) - len(finite),
    )
