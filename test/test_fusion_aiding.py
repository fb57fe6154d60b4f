"""The tracker with anchors and odometry: GNSS fixes make the site biases observable and are tested
against the track; odometry in a frame of unknown yaw is aligned and carries the track; the site
biases fade with the distance travelled; motion models set the stacks and the tracker.

Routes are simulated as in test_fusion_tracker (a walker among six sites 300-1100 m away), with
each site's range long by its own constant bias, GNSS fixes drawn from the truth, and odometry
seen from a frame turned by a yaw the tracker is not told.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from deepsync.fusion.aiding import (PositionAid, VelocityAid, frame_offset, heading_offset, odometry_velocity,
                                    rotation)
from deepsync.fusion.stage import FusionConfig, FusionStage
from deepsync.fusion.tracker import Tracker, TrackerConfig
from deepsync.motion import DEFAULT_MOTION, MOTION_MODELS, motion_model
from deepsync.pipeline import PipelineConfig
from deepsync.types import (
    UNMEASURED_VARIANCE,
    Fix,
    GnssFix,
    HealthKind,
    NoFix,
    NoFixReason,
    OdometryVelocity,
    PositionPrior,
    wrap_angle,
)
from test_fusion_tracker import SITES, Route, horizontal_error, nees, random_sites

BIASES_M = {"A": 35.0, "B": -20.0, "C": 60.0, "D": 0.0, "E": -45.0, "F": 25.0}


def biased_route(seed: int, duration_s: float, velocity: tuple[float, float] = (1.0, 1.0), **kwargs) -> Route:
    return Route(np.random.default_rng(seed), duration_s, random_sites(2, 3), noise_m=lambda t: 10.0, sigma_m=10.0,
                 site_errors={name: (bias, 0.0) for name, bias in BIASES_M.items()}, bias_std_m=40.0,
                 velocity=velocity, **kwargs)


def fix_at(route: Route, k: int, std_m: float, rng: np.random.Generator) -> PositionAid:
    truth = route.truth[k]
    position = truth + np.array([*rng.normal(0.0, std_m, 2), 0.0])
    return PositionAid(float(route.ends[k]), position, np.diag([std_m**2, std_m**2, UNMEASURED_VARIANCE]))


def run(route: Route, tracker: Tracker, aids: dict[int, list] | None = None) -> list[Fix | NoFix]:
    """The route through ``tracker``, each stack's aids queued before it."""
    outcomes = []
    for k, (arrivals, end) in enumerate(zip(route.stacks, route.ends)):
        for aid in (aids or {}).get(k, []):
            (tracker.add_position if isinstance(aid, PositionAid) else tracker.add_velocity)(aid)
        outcomes.append(tracker.update(arrivals, round(end * 1e9), float(end)))
    return outcomes


# --------------------------------------------------------------------------- anchors


def test_with_gnss_fixes_the_site_biases_converge_to_the_truth_within_their_sigma():
    """Observability: with the position pinned, what is left of each range is its site's bias
    (less what every site shares, the receiver clock's): each learned bias, against the mean of
    them all, lands within 3 of its sigmas of the true bias against the true mean."""
    rng = np.random.default_rng(3)
    route = biased_route(3, 60.0, velocity=(0.0, 0.0), moving=False)
    config = TrackerConfig(bias_correlation_s=1e6)  # a receiver that stands: its biases stay
    tracker = Tracker(config)
    aids = {k: [fix_at(route, k, 3.0, rng)] for k in range(0, len(route.ends), 20)}  # every 2 s
    outcomes = run(route, tracker, aids)
    assert isinstance(outcomes[-1], Fix)
    learned, stds = centred_biases(tracker)
    assert set(learned) == set(SITES)
    mean_true = np.mean([BIASES_M[name] for name in learned])
    for name, bias in learned.items():
        error = bias - (BIASES_M[name] - mean_true)
        assert abs(error) < 3 * stds[name], (name, error, stds[name])
        assert stds[name] < 10.0  # learned, not the 40 m prior
    # without the fixes the same biases stay near their prior: nothing pins them
    unanchored = Tracker(config)
    run(route, unanchored)
    assert np.median(list(centred_biases(unanchored)[1].values())) > 2 * np.median(list(stds.values()))


def centred_biases(tracker: Tracker) -> tuple[dict[str, float], dict[str, float]]:
    """Each site's learned bias (its persistent and fading parts) less the mean of them all, and
    its 1-sigma: what the sites can tell (the mean goes with the receiver clock)."""
    names = list(tracker._sites)
    total = np.zeros((len(names), len(tracker._x)))  # each site's bias: the sum of its two parts
    for row, name in enumerate(names):
        total[row, tracker._sites[name].index: tracker._sites[name].index + 2] = 1.0
    centred = (np.eye(len(names)) - 1.0 / len(names)) @ total
    covariance = centred @ tracker._P @ centred.T
    return dict(zip(names, centred @ tracker._x)), dict(zip(names, np.sqrt(np.diag(covariance))))


def test_a_fix_far_from_a_confident_track_is_refused_said_and_two_that_agree_restart_the_track():
    rng = np.random.default_rng(4)
    route = biased_route(4, 40.0)
    tracker = Tracker()
    far = np.array([1000.0, 0.0, 0.0])
    aids = {k: [fix_at(route, k, 3.0, rng)] for k in (20, 40)}
    stray = fix_at(route, 150, 3.0, rng)
    aids[150] = [PositionAid(stray.time_s, stray.position_enu + far, stray.covariance)]
    outcomes = run(route, tracker, aids)
    notes = tracker.take_notes()
    assert len(notes) == 1 and f"GNSS fix at {route.ends[150]:.1f} s refused: " in notes[0]
    assert 900 < float(notes[0].split("refused: ")[1].split(" m from the track")[0]) < 1100
    assert all(horizontal_error(fix, truth) < 60.0 for fix, truth in zip(outcomes[150:], route.truth[150:]))
    # a track that is confidently wrong (held by a wrong initial position, one site heard, which
    # cannot tell): the first fix is refused, the second agrees with it and the track goes to them
    lonely = Route(np.random.default_rng(5), 20.0, random_sites(1, 1, "A"))
    tracker = Tracker()
    tracker.start_from(PositionPrior(tuple(lonely.truth[0] + [300.0, 0.0, 0.0]), np.diag([25.0, 25.0, 1e6])))
    aids = {k: [fix_at(lonely, k, 3.0, rng)] for k in (50, 70)}
    outcomes = run(lonely, tracker, aids)
    assert horizontal_error(outcomes[49], lonely.truth[49]) > 250.0
    assert "refused" in " ".join(tracker.take_notes())
    assert tracker.last_restart is not None and "the track, not the fixes, was wrong" in tracker.last_restart
    assert horizontal_error(outcomes[80], lonely.truth[80]) < 30.0


def test_a_gnss_fix_starts_the_tracker_from_one_site():
    route = Route(np.random.default_rng(6), 5.0, random_sites(1, 1, "A"))
    tracker = Tracker()
    assert isinstance(tracker.update(route.stacks[0], 1, float(route.ends[0])), NoFix)
    aids = {1: [fix_at(route, 1, 5.0, np.random.default_rng(0))]}
    outcomes = run(route, tracker, aids)
    assert isinstance(outcomes[1], Fix) and horizontal_error(outcomes[1], route.truth[1]) < 20.0


def test_stale_aiding_is_refused_and_said():
    route = biased_route(7, 5.0)
    tracker = Tracker()
    run(route, tracker)
    tracker.add_position(fix_at(route, 5, 3.0, np.random.default_rng(0)))
    tracker.update([], 1, float(route.ends[-1]) + 0.1)
    (note,) = tracker.take_notes()
    assert "older than the track" in note


# --------------------------------------------------------------------------- bias decorrelation


def bias_variance_after(speed_mps: float, seconds: float, config: TrackerConfig) -> float:
    """A site bias state learned exactly, then left unheard while the receiver moves at ``speed_mps``."""
    tracker = Tracker(config)
    route = Route(np.random.default_rng(8), 3.0, random_sites(3, 3, "ABC"), velocity=(speed_mps, 0.0), moving=False,
                  bias_std_m=40.0)
    run(route, tracker)
    tracker._x[2:4] = [speed_mps, 0.0]
    tracker._P[2:4, :] = tracker._P[:, 2:4] = 0.0  # the velocity known exactly
    fading = tracker._sites["A"].index + 1  # after the persistent part, which does not fade
    tracker._P[fading, :] = tracker._P[:, fading] = 0.0
    tracker._predict(seconds)
    return float(tracker._P[fading, fading])


@pytest.mark.parametrize("speed_mps, seconds", [(1.4, 10.0), (14.0, 1.0), (0.0, 60.0), (1.4, 60.0)])
def test_a_site_bias_fades_over_the_distance_travelled_and_its_time(speed_mps, seconds):
    config = TrackerConfig(acceleration_std_mps2=1e-6)  # the velocity stays known over the step
    sigma2 = (1 - config.persistent_bias_fraction) * 40.0**2  # the fading part's stationary variance
    fade = seconds / config.bias_correlation_s + speed_mps * seconds / config.bias_decorrelation_m
    expected = sigma2 * -math.expm1(-2 * fade)
    assert bias_variance_after(speed_mps, seconds, config) == pytest.approx(expected, rel=0.02)


def test_a_car_forgets_a_bias_in_the_time_a_walker_keeps_it():
    config = TrackerConfig(acceleration_std_mps2=1e-6)
    walker, car = bias_variance_after(1.4, 3.0, config), bias_variance_after(14.0, 3.0, config)
    fading = (1 - config.persistent_bias_fraction) * 40.0**2
    assert walker < 0.2 * fading < 0.8 * fading < car


# --------------------------------------------------------------------------- odometry


def odometry(route: Route, yaw: float, scale: float, rng: np.random.Generator, std: float = 0.05,
             every: int = 1) -> dict[int, list[VelocityAid]]:
    """Velocity aids at stack ends, seen from a frame turned by ``yaw`` and scaled by ``scale``."""
    aids = {}
    velocities = np.diff(route.truth[:, :2], axis=0) / np.diff(route.ends)[:, None]
    for k in range(1, len(route.ends) - 1, every):
        v = velocities[k]
        sigma = math.hypot(std * float(np.hypot(*v)), 0.02)
        seen = (1 + scale) * rotation(-yaw) @ v + rng.normal(0.0, sigma, 2)
        aids[k] = [VelocityAid(float(route.ends[k]), seen, np.eye(2) * sigma**2)]
    return aids


def test_odometry_in_a_turned_frame_is_aligned_and_carries_the_track():
    """Odometry in a frame turned 2 rad from map, 3 % short: the yaw is found within its sigma
    from the stretch the track and the odometry both measured between two fixes 30 s apart,
    and with it the track for the 30 s after the second is better than without it."""
    rng = np.random.default_rng(9)
    route = biased_route(9, 70.0, velocity=(1.4, 0.3))
    fixes = {k: [fix_at(route, k, 3.0, rng)] for k in (5, 300)}
    with_odometry = Tracker()
    aids = odometry(route, 2.0, -0.03, rng)
    for k, fix in fixes.items():
        aids.setdefault(k, []).extend(fix)
    outcomes = run(route, with_odometry, aids)
    index = with_odometry._odometry
    assert index is not None, "the odometry frame was never aligned"
    psi, psi_std = with_odometry._x[index], math.sqrt(with_odometry._P[index, index])
    assert abs((psi - 2.0 + math.pi) % (2 * math.pi) - math.pi) < 3 * psi_std and psi_std < 0.15
    without = run(route, Tracker(), fixes)
    span = slice(320, 620)
    errors = [np.median([horizontal_error(fix, truth) for fix, truth in zip(outs[span], route.truth[span])])
              for outs in (outcomes, without)]
    assert errors[0] < errors[1]
    assert np.mean([nees(fix, truth) for fix, truth in zip(outcomes[span], route.truth[span])]) < 6.0


def test_odometry_in_map_has_its_scale_learned_and_the_track_stays_within_its_claim():
    """A velocity already in map (a robot whose odometry is turned into map) knows its yaw but
    not its wheels' scale: 6 % long, with a GNSS fix every 15 s on a drive, the scale is learned
    (5-8 % on four draws, 1-sigma 1.1-1.2 %) and the track between fixes stays within its claim
    (NEES 1.0-3.8 on four draws). Taken as the truth with white noise only, the scale error piled
    up between fixes as position error the track did not claim (NEES 36-58 here; the route set's
    drives with GNSS every 60 s, 12-15)."""
    rng = np.random.default_rng(4)
    route = biased_route(4, 60.0, velocity=(10.0, 3.0))
    aids = {k: [VelocityAid(v.time_s, v.velocity, v.covariance, in_map_frame=True) for v in velocity]
            for k, velocity in odometry(route, 0.0, 0.06, rng).items()}
    for k in range(5, len(route.ends), 150):
        aids.setdefault(k, []).append(fix_at(route, k, 3.0, rng))
    tracker = Tracker(PipelineConfig.for_motion("vehicle").fusion.tracker)
    outcomes = run(route, tracker, aids)
    assert tracker._odometry is not None, "map-frame odometry has no scale state"
    s = tracker._odometry + 1
    scale, scale_std = tracker._x[s], math.sqrt(tracker._P[s, s])
    assert 0.03 < scale < 0.12 and scale_std < 0.03
    assert abs(tracker._x[tracker._odometry]) < 0.05  # its yaw stays the map's
    later = [nees(fix, truth) for fix, truth in zip(outcomes[160:], route.truth[160:]) if isinstance(fix, Fix)]
    assert len(later) > 300 and np.mean(later) < 4.0


def with_headings(route: Route, aids: dict[int, list[VelocityAid]], yaw: float) -> dict[int, list[VelocityAid]]:
    """The same velocities, each with the body's heading in the odometry frame (facing the way
    it moves), as a robot's odometry pose gives it."""
    velocities = np.diff(route.truth[:, :2], axis=0) / np.diff(route.ends)[:, None]
    return {k: [VelocityAid(a.time_s, a.velocity, a.covariance, False,
                            math.atan2(velocities[k][1], velocities[k][0]) - yaw) for a in v] for k, v in aids.items()}


def test_an_initial_pose_with_a_heading_aligns_the_odometry_at_once():
    """An operator's pose that faces the way the receiver moves (0.05 rad off) and the
    odometry's own heading give the frame's yaw (2 rad) from the first velocity, within its
    sigma; without the heading the frame is still unknown seconds later (it waits for a
    stretch). A heading the odometry's comes more than 2 s after is dropped, and said."""
    rng = np.random.default_rng(15)
    route = biased_route(15, 20.0, velocity=(1.4, 0.3))
    aids = with_headings(route, odometry(route, 2.0, -0.03, rng), 2.0)
    facing = math.atan2(0.3, 1.4)
    here = route.truth[0]
    prior = PositionPrior(tuple(here + [3.0, -2.0, 0.0]), np.diag([25.0, 25.0, UNMEASURED_VARIANCE]), facing + 0.05,
                          0.05)
    outcomes = {}
    for heading in (True, False):
        tracker = Tracker()
        tracker.start_from(prior if heading else PositionPrior(prior.position_enu, prior.covariance))
        run(route, tracker, {k: v for k, v in aids.items() if k <= 20})
        outcomes[heading] = tracker
    aligned = outcomes[True]
    assert aligned._odometry is not None and outcomes[False]._odometry is None
    psi, psi_std = aligned._x[aligned._odometry], math.sqrt(aligned._P[aligned._odometry, aligned._odometry])
    assert abs(psi - 2.05) < 1e-6 + 3 * psi_std and psi_std < 0.1  # the prior's own 0.05 rad error, claimed
    late = Tracker()
    late.start_from(prior)
    run(route, late, {k: v for k, v in aids.items() if 40 <= k <= 100})  # 4-10 s: too short a stretch to align
    assert late._odometry is None
    assert any("heading was not used" in note for note in late.take_notes())


def frame_after_fixes(route: Route, aids: dict[int, list], fixes: tuple[int, ...], rng: np.random.Generator,
                      tracker: Tracker) -> list[tuple[int, np.ndarray, np.ndarray] | None]:
    """The route through ``tracker`` with GNSS fixes (3 m) at ``fixes`` besides ``aids``; the
    odometry frame (stack, values, covariance) after each stack, None before it is known."""
    aids = {k: list(v) for k, v in aids.items()}
    for k in fixes:
        aids.setdefault(k, []).append(fix_at(route, k, 3.0, rng))
    frames = []
    for k, (arrivals, end) in enumerate(zip(route.stacks, route.ends)):
        for aid in aids.get(k, []):
            (tracker.add_position if isinstance(aid, PositionAid) else tracker.add_velocity)(aid)
        tracker.update(arrivals, round(end * 1e9), float(end))
        block = None if tracker._odometry is None else slice(tracker._odometry, tracker._odometry + 2)
        frames.append(None if block is None else (k, tracker._x[block].copy(), tracker._P[block, block].copy()))
    return frames


def test_two_fixes_align_the_odometry_frame_where_the_track_cannot():
    """A drive whose track is too vague for its own displacement to say where the odometry
    frame points (a lost track keeps no stretch): the fixes at 0.5 and 30.5 s and the
    odometry read between them give the yaw (2 rad) and the scale (-3 %) at the second fix,
    within their sigmas, the yaw to 0.03 rad and the scale better than its 5 % prior. With
    3 s of odometry missing between the fixes they say nothing, and the frame stays unknown."""
    rng = np.random.default_rng(21)
    route = biased_route(21, 40.0, velocity=(10.0, 3.0))
    config = replace(PipelineConfig.for_motion("vehicle").fusion.tracker, max_std_m=1.0)
    aids = odometry(route, 2.0, -0.03, rng)
    tracker = Tracker(config)
    frames = frame_after_fixes(route, aids, (5, 305), rng, tracker)
    assert all(frame is None for frame in frames[:305]), "aligned before the second fix"
    _, (psi, scale), covariance = frames[305]
    psi_std, scale_std = np.sqrt(np.diag(covariance))
    assert abs(wrap_angle(psi - 2.0)) < 3 * psi_std and psi_std < 0.03
    assert abs(scale + 0.03) < 3 * scale_std and scale_std < 0.02
    said = tracker.odometry_frame()  # what the diagnostics show: the state's frame at the end
    _, (psi, scale), covariance = frames[-1]
    assert (said.yaw_rad, said.scale) == pytest.approx((wrap_angle(psi), scale))
    assert (said.yaw_std_rad, said.scale_std) == pytest.approx(tuple(np.sqrt(np.diag(covariance))))
    gap = {k: v for k, v in aids.items() if not 100 <= k < 130}
    assert frame_after_fixes(route, gap, (5, 305), rng, Tracker(config))[-1] is None


def test_fixes_every_second_align_the_odometry_frame_once_far_enough_apart():
    """A fix a second on a drive (10 m apart, too near to say a direction): the first stays the
    pair's first until one is far enough from it, and the frame is aligned within seconds."""
    rng = np.random.default_rng(24)
    route = biased_route(24, 12.0, velocity=(10.0, 3.0))
    config = replace(PipelineConfig.for_motion("vehicle").fusion.tracker, max_std_m=1.0)
    frames = frame_after_fixes(route, odometry(route, 2.0, -0.03, rng), tuple(range(5, 120, 10)), rng,
                               Tracker(config))
    aligned = next(frame for frame in frames if frame is not None)
    k, (psi, _), covariance = aligned
    assert k <= 45 and abs(wrap_angle(psi - 2.0)) < 3 * math.sqrt(covariance[0, 0]) < 0.6


def test_two_fixes_align_the_odometry_frame_while_no_track_runs():
    """No site heard: the fixes wait as initial positions and no track starts, but the two and
    the odometry read between them still say the frame, kept for the next track."""
    rng = np.random.default_rng(23)
    route = biased_route(23, 32.0, velocity=(10.0, 3.0))
    tracker = Tracker(PipelineConfig.for_motion("vehicle").fusion.tracker)
    aids = odometry(route, 2.0, -0.03, rng)
    for k in (5, 305):
        aids.setdefault(k, []).append(fix_at(route, k, 3.0, rng))
    known = []
    for k, end in enumerate(route.ends):
        for aid in aids.get(k, []):
            (tracker.add_position if isinstance(aid, PositionAid) else tracker.add_velocity)(aid)
        assert isinstance(tracker.update([], round(end * 1e9), float(end)), NoFix)
        known.append(tracker._odometry_known)
    assert all(frame is None for frame in known[:305])
    (psi, scale), covariance = known[305]
    psi_std, scale_std = np.sqrt(np.diag(covariance))
    assert abs(wrap_angle(psi - 2.0)) < 3 * psi_std and psi_std < 0.03
    assert abs(scale + 0.03) < 3 * scale_std and scale_std < 0.02
    said = tracker.odometry_frame()
    assert said is not None and said.yaw_rad == pytest.approx(wrap_angle(known[-1][0][0]))


@pytest.mark.parametrize("off_m", [0.0, 60.0])
def test_a_pair_of_fixes_that_disagrees_with_the_frame_known_is_not_used_and_said(off_m):
    """No site heard, fixes at 0.5, 30.5 and 60.5 s on a drive: the first pair aligns the frame;
    the third fix, 60 m off across the way, reads a yaw 0.2 rad from it (its sigma 0.03): that
    pair is refused, said, and the frame kept as it was; a third fix as good as the others
    narrows it instead."""
    rng = np.random.default_rng(25)
    route = biased_route(25, 62.0, velocity=(10.0, 3.0))
    tracker = Tracker(PipelineConfig.for_motion("vehicle").fusion.tracker)
    aids = odometry(route, 2.0, -0.03, rng)
    for k in (5, 305, 605):
        fix = fix_at(route, k, 3.0, rng)
        across = np.array([-3.0, 10.0, 0.0]) / math.hypot(3.0, 10.0)
        aids.setdefault(k, []).append(PositionAid(fix.time_s, fix.position_enu + (off_m * across if k == 605 else 0.0),
                                                  fix.covariance))
    known = []
    for k, end in enumerate(route.ends):
        for aid in aids.get(k, []):
            (tracker.add_position if isinstance(aid, PositionAid) else tracker.add_velocity)(aid)
        tracker.update([], round(end * 1e9), float(end))
        known.append(tracker._odometry_known)
    notes = " ".join(tracker.take_notes())
    first, last = known[305], known[605]
    if off_m:
        assert "the pair is not used" in notes
        assert np.array_equal(last[0], first[0]) and np.array_equal(last[1], first[1])
    else:
        assert "the pair is not used" not in notes
        assert last[1][0, 0] < first[1][0, 0] and abs(wrap_angle(last[0][0] - 2.0)) < 3 * math.sqrt(last[1][0, 0])


def test_two_fixes_turn_an_odometry_frame_aligned_wrong():
    """An operator's heading 0.4 rad off, claimed to 0.3, aligns the frame 0.4 rad off; the
    next pair of fixes, 30 s apart on a drive, turns it to within 0.05 rad of the truth."""
    rng = np.random.default_rng(22)
    route = biased_route(22, 40.0, velocity=(10.0, 3.0))
    aids = with_headings(route, odometry(route, 2.0, 0.0, rng), 2.0)
    facing = math.atan2(3.0, 10.0)
    tracker = Tracker(PipelineConfig.for_motion("vehicle").fusion.tracker)
    tracker.start_from(PositionPrior(tuple(route.truth[0]), np.diag([9.0, 9.0, UNMEASURED_VARIANCE]), facing + 0.4, 0.3))
    frames = frame_after_fixes(route, aids, (5, 305), rng, tracker)
    assert abs(wrap_angle(frames[4][1][0] - 2.4)) < 0.05  # the operator's word, before any fix
    assert abs(wrap_angle(frames[305][1][0] - 2.0)) < 0.05


def test_frame_offset_reads_yaw_and_scale_with_their_gradients():
    """A vector and the odometry's reading of it, turned 0.7 rad and 3 % long: the yaw and
    scale back, and their Jacobian by the map's vector and the covariance the odometry's noise
    adds as finite differences give them."""
    in_map, psi, scale = np.array([30.0, -40.0]), 0.7, 0.03
    in_odometry = (1 + scale) * rotation(-psi) @ in_map
    noise = np.array([[4.0, 1.0], [1.0, 2.0]])
    values, by_map, covariance = frame_offset(in_map, in_odometry, noise)
    assert values == pytest.approx([psi, scale])
    step = 1e-6
    by_odometry = np.zeros((2, 2))
    for k in range(2):
        d = np.zeros(2)
        d[k] = step
        assert np.allclose((frame_offset(in_map + d, in_odometry, noise)[0] - values) / step, by_map[:, k], atol=1e-6)
        by_odometry[:, k] = (frame_offset(in_map, in_odometry + d, noise)[0] - values) / step
    assert np.allclose(covariance, by_odometry @ noise @ by_odometry.T, rtol=1e-4)


def test_an_odometry_velocity_moves_the_velocity_and_not_the_position():
    """Through the motion model's position-velocity covariance each odometry velocity also moved
    the position, as if the odometry's slow errors were accelerations: a city walk without sites
    ran 25 m from its own odometry's path in a minute (within 2 m now)."""
    rng = np.random.default_rng(15)
    route = biased_route(15, 20.0, velocity=(1.4, 0.3))
    aids = with_headings(route, odometry(route, 2.0, -0.03, rng), 2.0)
    tracker = Tracker()
    tracker.start_from(PositionPrior(tuple(route.truth[0]), np.diag([25.0, 25.0, UNMEASURED_VARIANCE]),
                                     math.atan2(0.3, 1.4), 0.05))
    run(route, tracker, {k: v for k, v in aids.items() if k <= 20})
    assert tracker._odometry is not None
    before = tracker._x.copy()
    last = aids[20][0]
    tracker._use_velocity(VelocityAid(last.time_s, last.velocity * 1.2, last.covariance, False, last.heading_rad))
    assert np.array_equal(tracker._x[:2], before[:2])  # where it is: the sites' and anchors' to say
    assert not np.allclose(tracker._x[2:4], before[2:4])  # how it moves: the odometry's


def test_the_odometry_frame_found_outlives_a_restart_of_the_track():
    """Two fixes that agree far off the track restart it (and the sites, which disagree with
    them, restart it again): the yaw and scale already found are kept through every restart,
    not lost (they were read after the state was cleared, and a restarted track raised)."""
    rng = np.random.default_rng(9)
    route = biased_route(9, 70.0, velocity=(1.4, 0.3))
    aids = odometry(route, 2.0, -0.03, rng)
    for k in (5, 300):
        aids.setdefault(k, []).append(fix_at(route, k, 3.0, rng))
    tracker = Tracker()
    outcomes, found = [], None
    for k, (arrivals, end) in enumerate(zip(route.stacks, route.ends)):
        if k in (400, 420):  # the track "was wrong": the receiver is 800 m east
            moved = fix_at(route, k, 3.0, rng)
            tracker.add_position(PositionAid(moved.time_s, moved.position_enu + [800.0, 0.0, 0.0], moved.covariance))
        if k == 420:
            block = slice(tracker._odometry, tracker._odometry + 2)
            found = (tracker._x[block].copy(), tracker._P[block, block].copy())
        for aid in aids.get(k, []):
            (tracker.add_position if isinstance(aid, PositionAid) else tracker.add_velocity)(aid)
        outcomes.append(tracker.update(arrivals, round(end * 1e9), float(end)))
    assert found is not None and tracker.last_restart is not None
    assert isinstance(outcomes[-1], Fix)
    block = slice(tracker._odometry, tracker._odometry + 2)
    kept, spread = tracker._x[block], np.diag(tracker._P[block, block])
    assert np.allclose(kept, found[0], atol=1e-9)  # considered, not updated: the same values
    assert np.all(spread >= np.diag(found[1])) and np.all(spread < 1.1 * np.diag(found[1]))  # their drift only


def test_odometry_standing_still_says_so_before_any_alignment():
    route = Route(np.random.default_rng(10), 20.0, random_sites(2, 3), moving=False, velocity=(0.0, 0.0))
    aids = {k: [VelocityAid(float(route.ends[k]), np.zeros(2), np.eye(2) * 0.02**2)] for k in range(5, 200)}
    still, free = Tracker(), Tracker()
    run(route, still, aids)
    run(route, free)
    assert still._odometry is None
    assert np.trace(still._P[2:4, 2:4]) < 0.01 * np.trace(free._P[2:4, 2:4])


def test_odometry_that_keeps_disagreeing_turns_the_tracks_velocity():
    """A turn the motion model does not expect: the odometry says it three times, and the track's
    velocity follows it instead of refusing it for ever."""
    tracker = Tracker()
    route = biased_route(11, 30.0, velocity=(1.4, 0.0))
    rng = np.random.default_rng(11)
    aids = odometry(route, 0.5, 0.0, rng)
    aids.setdefault(3, []).append(fix_at(route, 3, 3.0, rng))
    aids.setdefault(250, []).append(fix_at(route, 250, 3.0, rng))
    run(route, tracker, aids)
    assert tracker._odometry is not None
    # the receiver now reports 1.4 m/s north where it went east: after a few refusals, taken
    t = float(route.ends[-1])
    for k in range(10):
        tracker.add_velocity(VelocityAid(t + 0.1 * (k + 1), rotation(-0.5) @ np.array([0.0, 1.4]), np.eye(2) * 0.05**2))
    tracker.update([], 1, t + 1.05)
    notes = " ".join(tracker.take_notes())
    assert "refused" in notes and "the track's velocity was wrong" in notes
    assert tracker._x[3] > 1.0 and abs(tracker._x[2]) < 0.5


def test_odometry_model_and_heading_gradients_match_finite_differences():
    v, psi, scale = np.array([1.3, -0.4]), 0.7, 0.02
    seen, by_v, by_psi, by_scale = odometry_velocity(v, psi, scale)
    step = 1e-6
    for k in range(2):
        dv = np.zeros(2)
        dv[k] = step
        assert np.allclose((odometry_velocity(v + dv, psi, scale)[0] - seen) / step, by_v[:, k], atol=1e-5)
    assert np.allclose((odometry_velocity(v, psi + step, scale)[0] - seen) / step, by_psi, atol=1e-5)
    assert np.allclose((odometry_velocity(v, psi, scale + step)[0] - seen) / step, by_scale, atol=1e-5)
    odometry_frame = rotation(-psi) @ v
    found, by_track, _ = heading_offset(v, odometry_frame, np.eye(2) * 1e-4)
    assert found == pytest.approx(psi)
    dv = np.array([0.0, step])
    assert (heading_offset(v + dv, odometry_frame, np.eye(2))[0] - found) / step == pytest.approx(by_track[1], rel=1e-4)


# --------------------------------------------------------------------------- motion models and bad input


def test_each_motion_model_sets_the_stacks_and_the_tracker():
    for model in MOTION_MODELS.values():
        config = PipelineConfig.for_motion(model.name)
        assert (config.sync.stack.n_frames, config.sync.stack.hop) == (model.n_frames, model.hop_frames)
        assert config.fusion.tracker.acceleration_std_mps2 == model.acceleration_std_mps2
        assert config.fusion.tracker.initial_speed_std_mps == model.initial_speed_std_mps
        assert config.fusion.tracker.stack_overlap == model.n_frames / model.hop_frames
        assert config.fusion.multipath_std_m == model.multipath_std_m
        assert config.fusion.tracker.prior_hold_s == model.prior_hold_s
        assert config.fusion.tracker.spare_site_at_start is model.spare_site_at_start
        # a command line's explicit stacks and bias sigma win over the model's
        chosen = PipelineConfig().with_choices(motion=model.name, n_frames=10, multipath_std_m=33.0)
        assert chosen.sync.stack.hop == 10 and chosen.fusion.multipath_std_m == 33.0
    # one source: the fusion config's own default is the default motion model's
    assert FusionConfig().multipath_std_m == motion_model(DEFAULT_MOTION).multipath_std_m
    assert TrackerConfig().prior_hold_s == motion_model(DEFAULT_MOTION).prior_hold_s
    assert TrackerConfig().spare_site_at_start is motion_model(DEFAULT_MOTION).spare_site_at_start
    assert PipelineConfig() == PipelineConfig.for_motion("pedestrian")
    with pytest.raises(ValueError, match="'bicycle' is not one of pedestrian, vehicle, static"):
        motion_model("bicycle")


@pytest.mark.parametrize("field, value", [
    ("bias_decorrelation_m", 0.0), ("max_std_m", math.inf), ("max_position_rejections", 0),
    ("heading_drift_rad_per_sqrt_s", -1.0), ("odometry_scale_std", 0.0), ("odometry_scale_wander_per_sqrt_s", 2.0)])
def test_new_tracker_settings_are_checked_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        TrackerConfig(**{field: value})


@pytest.mark.parametrize("field, value", [("gnss_std_m", 0.0), ("gnss_min_std_m", math.nan),
                                          ("aiding_clock_window_s", -1.0)])
def test_new_fusion_settings_are_checked_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        FusionConfig(**{field: value})


@pytest.mark.parametrize("build, says", [
    (lambda: GnssFix(0, math.nan, 0.0, 0.0), "latitude_deg"),
    (lambda: GnssFix(0, 10.0, 200.0, 0.0), "longitude_deg"),
    (lambda: GnssFix(-1, 10.0, 20.0, 0.0), "stamp_ns"),
    (lambda: GnssFix(0, 10.0, 20.0, 0.0, np.diag([1.0, -1.0, 1.0])), "positive definite"),
    (lambda: OdometryVelocity(0, (math.inf, 0.0), np.eye(2)), "velocity"),
    (lambda: OdometryVelocity(0, (1.0, 0.0), np.zeros((2, 2))), "positive definite"),
    (lambda: OdometryVelocity(0, (1.0, 0.0), np.eye(2), False, math.nan), "heading_rad"),
    (lambda: PositionPrior((0.0, 0.0, 0.0), np.eye(3), 1.0), "give both or neither"),
    (lambda: PositionPrior((0.0, 0.0, 0.0), np.eye(3), math.inf, 0.1), "heading_rad"),
    (lambda: PositionPrior((0.0, 0.0, 0.0), np.eye(3), 1.0, 0.0), "heading_std_rad"),
    (lambda: PositionPrior((0.0, 0.0, 0.0), np.eye(3), 1.0, 4.0), "heading_std_rad"),
])
def test_aiding_that_is_not_a_measurement_is_refused_naming_the_field(build, says):
    with pytest.raises(ValueError, match=says):
        build()


def sites_stage(**config) -> FusionStage:
    """A fusion stage for a database of the simulated sites A-F (timing offsets 0 at the origin's epoch)."""
    from deepsync.geo import LocalFrame
    from deepsync.towers import parse_tower_database

    origin = {"latitude_deg": 38.98690, "longitude_deg": -76.94260, "height_m": 10.0}
    frame = LocalFrame(origin["latitude_deg"], origin["longitude_deg"], origin["height_m"])
    sites = []
    for k, (name, enu) in enumerate(SITES.items()):
        latitude, longitude, _ = frame.enu_to_geodetic(np.array([enu[0], enu[1], 0.0]))
        sites.append({"name": name, "latitude_deg": float(latitude), "longitude_deg": float(longitude),
                      "height_m": float(enu[2]), "timing_offset_us": 100.0 * (k + 1), "cells": [{"pci": k}]})
    towers = parse_tower_database({"name": "sites", "origin": origin, "timing_epoch_utc": "2026-01-01T00:00:00Z",
                                   "sites": sites})
    return FusionStage(towers, FusionConfig(**config))


def test_the_stage_refuses_aiding_back_in_time_on_another_clock_or_without_a_tracker():
    stage = sites_stage()
    fix = GnssFix(2_000_000_000, 38.98690, -76.94260, 10.0)
    assert stage.add_gnss(fix) is None
    refused = stage.add_gnss(GnssFix(1_000_000_000, 38.98690, -76.94260, 10.0))
    assert refused.kind is HealthKind.AIDING_REFUSED and "not after the one before" in refused.message
    velocity = OdometryVelocity(3_000_000_000, (1.0, 0.0), np.eye(2) * 0.01)
    assert stage.add_odometry(velocity) is None
    assert "not after" in stage.add_odometry(velocity).message  # the same stamp again
    assert "tracking is off" in sites_stage(track=False).add_gnss(fix).message


def test_a_fix_without_a_covariance_takes_the_configured_sigma_and_none_is_tighter_than_the_floor():
    stage = sites_stage(gnss_std_m=12.0, gnss_min_std_m=4.0)
    plain = stage._position_aid(GnssFix(0, 38.98690, -76.94260, 10.0), 0.0)
    assert np.allclose(np.diag(plain.covariance)[:2], 144.0)
    tight = stage._position_aid(GnssFix(0, 38.98690, -76.94260, 10.0, np.diag([0.01, 0.01, 0.04])), 0.0)
    assert np.allclose(np.diag(tight.covariance)[:2], 16.0)
    assert np.allclose(plain.position_enu[:2], 0.0, atol=1e-6)


def test_the_learned_database_holds_the_learned_biases_as_site_timing():
    """Biases learned on one run are the next run's site timing: a range that was long by the
    learned bias reads right with the learned database."""
    from deepsync.towers import parse_tower_database, tower_database_to_dict

    stage = sites_stage()
    assert stage.learned_database() is None  # nothing learned before a track
    stage.reference_ns = stage.anchors.epoch_ns
    tracker = stage.tracker
    run(biased_route(12, 5.0), tracker)
    learned = stage.learned_database()
    again = parse_tower_database(tower_database_to_dict(learned), "learned")
    for name, bias in tracker.site_biases().items():
        before = next(site for site in stage.anchors.towers.sites if site.name == name)
        after = next(site for site in again.sites if site.name == name)
        moved_m = (after.timing_offset_us - before.timing_offset_us) * 1e-6 * 299_792_458.0
        assert moved_m == pytest.approx(bias.bias_m, abs=0.5)
        assert after.timing_offset_std_us * 1e-6 * 299_792_458.0 == pytest.approx(bias.std_m, rel=1e-3)


def test_a_track_vaguer_than_max_std_m_is_reported_lost():
    route = Route(np.random.default_rng(13), 40.0, lambda k, rng: random_sites(3, 3)(k, rng) if k < 50 else ["A"])
    outcomes = route.track(TrackerConfig(max_std_m=60.0, max_coast_s=1000.0))
    lost = [o for o in outcomes if isinstance(o, NoFix) and o.reason is NoFixReason.TRACK_LOST]
    assert lost and "max_std_m 60 m" in lost[0].message
    assert all(o.horizontal_std_m <= 60.0 for o in outcomes if isinstance(o, Fix))


def test_odometry_that_stops_gives_the_velocity_back_to_the_sites():
    """While odometry comes, the sites do not move the velocity (the odometry measures it); once
    it has stopped for longer than a gap, they do again: the tracker runs on the sites and its
    motion model."""
    rng = np.random.default_rng(14)
    route = biased_route(14, 40.0, velocity=(1.4, 0.0))
    aids = {k: v for k, v in odometry(route, 1.0, 0.0, rng).items() if k < 200}
    for k in (3, 190):
        aids.setdefault(k, []).append(fix_at(route, k, 3.0, rng))
    tracker = Tracker()
    outcomes = run(route, tracker, aids)
    assert tracker._odometry is not None
    # the track goes on after the odometry stopped at 20 s, and stays within its claim
    late = [nees(fix, truth) for fix, truth in zip(outcomes[300::20], route.truth[300::20]) if isinstance(fix, Fix)]
    assert late and np.mean(late) < 6.0


def test_a_plan_draws_the_same_fixes_for_the_same_seed_and_one_at_the_start_for_interval_0():
    from deepsync.eval.aiding import AidingPlan
    from deepsync.geo import LocalFrame

    frame = LocalFrame(38.98690, -76.94260, 10.0)
    stamps = np.arange(0, 61) * 1_000_000_000
    positions = np.column_stack([1.4 * np.arange(61.0), np.zeros(61), np.full(61, 1.5)])

    def position_at(stamp: int) -> np.ndarray:
        return positions[int(stamp // 1_000_000_000)]

    every = AidingPlan(20.0, 5.0, seed=3).gnss_fixes(0, 60_000_000_000, position_at, frame)
    assert [fix.stamp_ns // 1_000_000_000 for fix in every] == [0, 20, 40, 60]
    assert every == AidingPlan(20.0, 5.0, seed=3).gnss_fixes(0, 60_000_000_000, position_at, frame)
    assert every != AidingPlan(20.0, 5.0, seed=4).gnss_fixes(0, 60_000_000_000, position_at, frame)
    assert len(AidingPlan(0.0).gnss_fixes(0, 60_000_000_000, position_at, frame)) == 1
    # a set of routes: each recording draws its own, the same for the same recording
    walk = AidingPlan(20.0, 5.0, seed=3).for_recording("city_walk_day_s1")
    assert walk.gnss_fixes(0, 60_000_000_000, position_at, frame) != every
    assert walk == AidingPlan(20.0, 5.0, seed=3).for_recording("city_walk_day_s1")
    assert walk != AidingPlan(20.0, 5.0, seed=3).for_recording("city_walk_day_s2")
    assert walk.gnss_interval_s == 20.0 and walk.gnss_std_m == 5.0
    velocities = AidingPlan(odometry_std=0.05).odometry(0, 60_000_000_000, stamps, positions)
    speeds = [math.hypot(*v.velocity) for v in velocities]
    assert len(velocities) == 600 and abs(np.median(speeds) - 1.4) < 0.15  # 1.4 m/s, a 5 % scale at most ~2 sigma
    # turned into map, the same velocities point east (the truth's way) within the yaw's wander
    in_map = AidingPlan(odometry_std=0.05, odometry_in_map=True).odometry(0, 60_000_000_000, stamps, positions)
    assert all(v.in_map_frame for v in in_map) and not any(v.in_map_frame for v in velocities)
    assert np.median([math.hypot(*v.velocity) for v in in_map]) == pytest.approx(np.median(speeds), abs=0.02)
    assert abs(np.median([math.atan2(v.velocity[1], v.velocity[0]) for v in in_map])) < 0.05
    assert abs(np.median([math.atan2(v.velocity[1], v.velocity[0]) for v in velocities])) > 0.1
    with pytest.raises(ValueError, match="gnss_interval_s"):
        AidingPlan(-1.0)
    with pytest.raises(ValueError, match="odometry_in_map"):
        AidingPlan(odometry_std=0.05, odometry_in_map=1)
    with pytest.raises(ValueError, match="odometry_std"):
        AidingPlan(odometry_std=2.0)


def test_no_pose_vaguer_than_max_std_m_is_published_the_stacks_own_included():
    from deepsync.fusion.stage import published_answer

    def snapshot(std_m: float) -> Fix:
        return Fix(7, (1.0, 2.0, 0.0), np.diag([std_m**2, std_m**2, UNMEASURED_VARIANCE]), ("A", "B", "C"))

    lost = NoFix(7, NoFixReason.TRACK_LOST, "lost")
    vague = published_answer(lost, lambda: snapshot(1500.0), 150.0)
    assert isinstance(vague, NoFix) and vague.reason is NoFixReason.DEGENERATE_GEOMETRY
    assert "2121 m 1-sigma, beyond max_std_m 150 m" in vague.message
    fair = snapshot(50.0)
    assert published_answer(lost, lambda: fair, 150.0) is fair
    tracked = snapshot(10.0)
    assert published_answer(tracked, lambda: snapshot(1500.0), 150.0) is tracked
