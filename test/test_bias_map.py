"""Site bias maps: the grid, its file, a survey, reading a map where the receiver is, fusion with
a map, and the commands and node parameters that make and take one.

Synthetic surveys walk among the six sites of test_fusion_snapshot with every site's range long
by its own smooth field of position (tens of metres, changing over tens of metres, as an NLOS
pull does) plus noise and a receiver clock offset common to each stack; a map must give back
each site's field against the other sites' (the part common to all is the receiver clock's).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from deepsync.cli import main
from deepsync.fusion.anchors import FRAME_RANGE_M, Anchors, SiteArrival, frame_reference_ns
from deepsync.fusion.bias_map import (
    BiasGrid,
    BiasMap,
    SurveyConfig,
    bias_map_from_points,
    load_bias_map,
    save_bias_map,
    survey_bias_map,
)
from deepsync.fusion.calibration import CalibrationObservation
from deepsync.fusion.stage import FusionConfig, FusionStage
from deepsync.pipeline import Pipeline
from deepsync.towers import load_tower_database
from deepsync.types import SPEED_OF_LIGHT_M_S, Fix
from deepsync_ros import params
from deepsync_ros.params import ParameterError
from test_fusion_snapshot import EPOCH_NS, FRAME_NS, ORIGIN, RATE, TOWERS, stack
from test_route_evaluation import envelope_only_bag

REPO = Path(__file__).resolve().parents[1]
ROUTE_BAG = REPO / "bags" / "campus_route"
CAMPUS_TOWERS = REPO / "config" / "towers" / "campus.yaml"
ORIGIN_TUPLE = (ORIGIN["latitude_deg"], ORIGIN["longitude_deg"], ORIGIN["height_m"])  # campus.yaml's too
ELSEWHERE = (ORIGIN_TUPLE[0] + 0.01, ORIGIN_TUPLE[1], ORIGIN_TUPLE[2])  # 1.1 km north
ANCHORS = Anchors(TOWERS)
SITE_NAMES = sorted(ANCHORS.anchors)
METRES_PER_SAMPLE = SPEED_OF_LIGHT_M_S / RATE


def true_bias(site: str, east: np.ndarray | float, north: np.ndarray | float) -> np.ndarray:
    """Site ``site``'s NLOS pull (m) at a point: 20-90 m, changing by tens of metres over 50 m."""
    k = SITE_NAMES.index(site)
    return 55.0 + 35.0 * np.sin(np.asarray(east) / 45.0 + 1.3 * k) * np.cos(np.asarray(north) / 60.0 - 0.7 * k)


def centred(values: dict[str, float]) -> dict[str, float]:
    """Each site's bias against the mean of them all: what TDOA can tell."""
    mean = float(np.mean(list(values.values())))
    return {site: value - mean for site, value in values.items()}


# -- the grid -----------------------------------------------------------------------------------


def test_grid_values_are_bilinear_between_known_nodes_and_nan_where_unknown() -> None:
    mean = np.array([[0.0, 10.0, np.nan], [20.0, 40.0, np.nan]])  # rows north, columns east
    std = np.array([[1.0, 3.0, np.nan], [5.0, 7.0, np.nan]])
    grid = BiasGrid(100.0, -50.0, 10.0, mean, std)
    east = np.array([100.0, 105.0, 100.0, 105.0, 110.0, 102.5])
    north = np.array([-50.0, -50.0, -45.0, -45.0, -40.0, -47.5])
    values, sigmas = grid.values(east, north)
    # at (105, -45): the four nodes' mean (0 + 10 + 20 + 40) / 4; at (102.5, -47.5) weights 9/16 3/16 3/16 1/16
    np.testing.assert_allclose(values, [0.0, 5.0, 10.0, 17.5, 40.0, 0.1875 * 10 + 0.1875 * 20 + 0.0625 * 40])
    np.testing.assert_allclose(sigmas, [1.0, 2.0, 3.0, 4.0, 7.0, 0.5625 * 1 + 0.1875 * 3 + 0.1875 * 5 + 0.0625 * 7])
    # a cell with unknown nodes: the known ones, renormalised
    assert grid.at(115.0, -50.0) == pytest.approx((10.0, 3.0))
    # outside the grid, or in the unknown column alone
    outside, _ = grid.values(np.array([99.9, 121.0, 105.0, 120.0]), np.array([-50.0, -50.0, -29.0, -45.0]))
    assert np.isnan(outside[:3]).all() and np.isnan(outside[3])
    assert grid.at(120.0, -45.0) is None


def test_a_grid_with_a_sigma_where_its_mean_is_unknown_is_refused() -> None:
    with pytest.raises(ValueError, match="exactly where its mean is known"):
        BiasGrid(0.0, 0.0, 10.0, np.array([[1.0, np.nan]]), np.array([[1.0, 1.0]]))
    with pytest.raises(ValueError, match="positive step"):
        BiasGrid(0.0, 0.0, 0.0, np.zeros((1, 1)), np.zeros((1, 1)))


# -- the file -----------------------------------------------------------------------------------


def small_map(origin: tuple[float, float, float] = ORIGIN_TUPLE) -> BiasMap:
    grid = BiasGrid(-20.0, 5.0, 10.0, np.array([[1.0, 2.0], [np.nan, 4.0]]), np.array([[0.5, 0.5], [np.nan, 1.5]]))
    other = BiasGrid(0.0, 0.0, 5.0, np.array([[-3.0]]), np.array([[2.0]]))
    return BiasMap(origin, {"S0": grid, "S3": other}, "a test", min_std_m=7.0)


def test_a_map_reads_back_as_it_was_written(tmp_path: Path) -> None:
    written = small_map()
    path = save_bias_map(written, tmp_path / "maps" / "site.npz")
    read = load_bias_map(path)
    assert read.origin == written.origin and read.made_by == "a test" and read.min_std_m == 7.0
    assert set(read.sites) == {"S0", "S3"}
    for name, grid in written.sites.items():
        again = read.sites[name]
        assert (again.x0_m, again.y0_m, again.step_m) == (grid.x0_m, grid.y0_m, grid.step_m)
        np.testing.assert_array_equal(again.mean_m, grid.mean_m)
        np.testing.assert_array_equal(again.std_m, grid.std_m)


def test_a_file_that_is_no_map_or_is_missing_is_refused_naming_it(tmp_path: Path) -> None:
    text = tmp_path / "notes.npz"
    text.write_text("not an archive")
    other = tmp_path / "arrays.npz"
    np.savez(other, x=np.zeros(3))
    for path, says in ((text, "not a DeepSync bias map"), (other, "not a DeepSync bias map"),
                       (tmp_path / "gone.npz", "does not exist")):
        with pytest.raises(ValueError, match=says) as refused:
            load_bias_map(path)
        assert str(path) in str(refused.value)


def test_a_map_made_in_another_frame_is_refused() -> None:
    moved = small_map(ELSEWHERE)
    small_map().check_database(TOWERS)  # its own frame
    with pytest.raises(ValueError, match="was made in the frame at .* tower database 'test' is at"):
        moved.check_database(TOWERS)
    with pytest.raises(ValueError, match="was made in the frame"):
        FusionStage(TOWERS, bias_map=moved)
    with pytest.raises(ValueError, match="there is no fusion"):
        Pipeline(None, towers=None, bias_map=small_map())


# -- a survey -----------------------------------------------------------------------------------


def arrivals_at(point: np.ndarray, sites: list[str], rng: np.random.Generator, noise_m: float,
                clock_m: float, time_s: float = 0.0, off_m: dict[str, float] | None = None) -> list[SiteArrival]:
    """The sites heard at ``point``: each range its distance, its pull, the stack's clock and noise."""
    heard = []
    for site in sites:
        position = ANCHORS.anchors[site].position_enu
        read = (float(np.linalg.norm(point - position)) + float(true_bias(site, point[0], point[1])) + clock_m
                + rng.normal(0.0, noise_m) + (off_m or {}).get(site, 0.0))
        heard.append(SiteArrival(site, position, time_s, read % FRAME_RANGE_M, max(noise_m, 1.0), (0,)))
    return heard


def walk(east_from: float = -150.0, east_to: float = 150.0, north: float = 20.0, step_m: float = 1.0) -> np.ndarray:
    east = np.arange(east_from, east_to + step_m / 2, step_m)
    return np.column_stack([east, np.full_like(east, north), np.full_like(east, 1.5)])


FALSE_LOCKS = {40: "S2", 130: "S4", 250: "S0"}  # stack index: the site that locked 5 km off


def surveyed(seed: int = 1) -> tuple[BiasMap, np.ndarray]:
    rng = np.random.default_rng(seed)
    points = walk()
    stacks = []
    for k, point in enumerate(points):
        off = {FALSE_LOCKS[k]: 5000.0} if k in FALSE_LOCKS else None
        heard = arrivals_at(point, SITE_NAMES, rng, 5.0, rng.uniform(-3e4, 3e4), off_m=off)
        stacks.append([CalibrationObservation(arrival, point) for arrival in heard])
    return survey_bias_map(stacks, ORIGIN_TUPLE, made_by="synthetic"), points


def test_a_map_corrects_the_range_and_never_narrows_the_sites_bias_sigma() -> None:
    """Read where the stack says the receiver is, a map may be read at the wrong place: its
    correction comes off the range, and the bias sigma stays the arrival's own (the map's where
    wider), so a wrong correction is one more bias of the size the sigma already covers."""
    grid = BiasGrid(0.0, 0.0, 10.0, np.full((3, 3), 40.0), np.full((3, 3), 12.0))
    bias_map = BiasMap(ORIGIN_TUPLE, {"A": grid})
    wide = SiteArrival("A", np.zeros(3), 0.0, 1000.0, 5.0, (1,), bias_std_m=100.0)
    narrow = SiteArrival("A", np.zeros(3), 0.0, 1000.0, 5.0, (1,), bias_std_m=3.0)
    unmapped = SiteArrival("B", np.zeros(3), 0.0, 1000.0, 5.0, (2,), bias_std_m=100.0)
    corrected = bias_map.correct([wide, narrow, unmapped], (10.0, 10.0, 0.0), 0.0)
    assert [a.range_mod_m for a in corrected] == [960.0, 960.0, 1000.0]
    assert [a.bias_std_m for a in corrected] == [100.0, 12.0, 100.0]


def test_a_survey_recovers_each_sites_pull_against_the_others_and_leaves_false_locks_out() -> None:
    bias_map, points = surveyed()
    assert set(bias_map.sites) == set(SITE_NAMES) and bias_map.origin == ORIGIN_TUPLE
    errors, ends = [], []
    for point in points[::5]:
        mapped = {site: bias_map.sites[site].at(point[0], point[1]) for site in SITE_NAMES}
        assert all(value is not None for value in mapped.values())
        got = centred({site: value[0] for site, value in mapped.items()})
        want = centred({site: float(true_bias(site, point[0], point[1])) for site in SITE_NAMES})
        # within two kernel sigmas of the walk's ends the kernel averages one side only: a pull
        # sloping by a metre per metre there reads up to about one sigma's slope off
        inside = abs(point[0]) <= 150.0 - 2 * SurveyConfig().smoothing_m
        (errors if inside else ends).extend(abs(got[site] - want[site]) for site in SITE_NAMES)
    # the pulls span 70 m; the map is within a few metres all along the survey
    assert np.max(errors) < 5.0 and np.median(errors) < 2.5, (np.max(errors), np.median(errors))
    assert np.max(ends) < 15.0
    # a 5 km false lock would have pulled its neighbourhood by kilometres
    for k, site in FALSE_LOCKS.items():
        value = bias_map.sites[site].at(points[k][0], points[k][1])[0]
        assert abs(value) < 150.0
    # the sigma is the spread a new run's arrival meets there: about the arrivals' 5 m of noise
    # (and the pull's slope within the kernel), not the kernel mean's centimetres, nor tens of metres
    sigma = bias_map.sites["S1"].at(0.0, 20.0)[1]
    assert 3.0 < sigma < 15.0


def test_a_survey_knows_only_where_it_went() -> None:
    bias_map, _ = surveyed()
    assert bias_map.sites["S0"].at(0.0, 20.0) is not None
    assert bias_map.sites["S0"].at(0.0, 20.0 + 2 * SurveyConfig().smoothing_m) is None  # across the street
    assert bias_map.at("S0", 400.0, 20.0) is None  # beyond the walk's end
    assert bias_map.at("nowhere", 0.0, 20.0) is None


def test_a_survey_without_two_sites_in_a_stack_is_refused() -> None:
    rng = np.random.default_rng(0)
    lonely = [[CalibrationObservation(a, p)] for p in walk() for a in arrivals_at(p, ["S0"], rng, 5.0, 0.0)]
    with pytest.raises(ValueError, match="two or more sites"):
        survey_bias_map(lonely, ORIGIN_TUPLE)
    with pytest.raises(ValueError, match="smoothing_m must be within"):
        SurveyConfig(smoothing_m=0.0)


# -- reading a map where the receiver is ----------------------------------------------------------


def test_locate_finds_where_on_the_survey_the_receiver_is_and_nothing_off_it() -> None:
    bias_map, _ = surveyed()
    rng = np.random.default_rng(7)
    for east in (-120.0, -37.0, 0.0, 64.0, 110.0):
        point = np.array([east, 20.0, 1.5])
        found = bias_map.locate(arrivals_at(point, SITE_NAMES, rng, 2.0, 1234.5))
        assert found is not None
        where, spread = found
        assert math.dist(where, point[:2]) <= 12.0, (east, where)
        assert 0.0 <= spread < 30.0
    # 250 m north of the walk: no node fits every site's range
    assert bias_map.locate(arrivals_at(np.array([0.0, 270.0, 1.5]), SITE_NAMES, rng, 2.0, 0.0)) is None
    # two mapped sites say nothing of where
    assert bias_map.locate(arrivals_at(np.array([0.0, 20.0, 1.5]), ["S0", "S1"], rng, 2.0, 0.0)) is None


# -- fusion with a map --------------------------------------------------------------------------


HOP_NS = 20 * FRAME_NS  # a stack every 0.2 s
SPEED_MPS = 1.4


def walked_stacks(seed: int, seconds: float = 150.0) -> list[tuple[np.ndarray, object]]:
    """(truth, the stack's arrivals) along the walk east at 1.4 m/s, every site late by its pull."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(int(seconds / (HOP_NS * 1e-9))):
        t = k * HOP_NS * 1e-9
        point = np.array([-100.0 + SPEED_MPS * t, 20.0, 1.5])
        shift = {j: float(true_bias(f"S{j}", point[0], point[1])) / METRES_PER_SAMPLE for j in range(6)}
        arrivals = stack(point, stamp_ns=EPOCH_NS + 37 * FRAME_NS + k * HOP_NS, toa_std=0.05,
                         noise_samples=rng.normal(0.0, 0.05, 6), shift_samples=shift)
        out.append((point, arrivals))
    return out


def fused_errors(stacks: list, bias_map: BiasMap | None) -> np.ndarray:
    # the sites' bias sigma of the size of these pulls (20-90 m), not a walker's 100 m, set for
    # the ray-traced city's: the map's correction is then what tells the two runs apart
    stage = FusionStage(TOWERS, FusionConfig(multipath_std_m=60.0), bias_map=bias_map)
    errors = []
    for truth, arrivals in stacks:
        tracked = stage.process(arrivals).tracked
        if isinstance(tracked, Fix):
            errors.append(math.dist(tracked.position_enu[:2], truth[:2]))
    return np.array(errors)


def test_fusion_with_a_survey_map_tracks_closer_than_without() -> None:
    survey = walked_stacks(seed=11)
    reference_ns = frame_reference_ns(survey[0][1].stamp_ns)
    stacks = []
    for truth, arrivals in survey:
        sites, problems = ANCHORS.site_arrivals(arrivals, reference_ns, 8.0)
        assert not problems
        stacks.append([CalibrationObservation(site, truth) for site in sites])
    bias_map = survey_bias_map(stacks, ORIGIN_TUPLE, made_by="the same walk, another day")
    run = walked_stacks(seed=12)
    without, mapped = fused_errors(run, None), fused_errors(run, bias_map)
    assert len(mapped) >= 0.9 * len(run) and len(without) >= 0.9 * len(run)
    assert np.median(mapped) < 0.75 * np.median(without), (np.median(mapped), np.median(without))
    assert np.median(mapped) < 11.0


# -- the commands and the node parameters --------------------------------------------------------


def test_survey_map_on_the_campus_walk_writes_a_map_evaluate_route_and_replay_take(tmp_path, capsys) -> None:
    out = tmp_path / "campus_map.npz"
    assert main(["survey-map", "--bag", str(ROUTE_BAG), "--towers", str(CAMPUS_TOWERS), "--out", str(out),
                 "--quiet"]) == 0
    printed = capsys.readouterr().out
    bias_map = load_bias_map(out)
    bias_map.check_database(load_tower_database(CAMPUS_TOWERS))
    assert set(bias_map.sites) == {"A", "B", "C"}
    for site, grid in bias_map.sites.items():
        known = int(np.isfinite(grid.mean_m).sum())
        assert known > 0 and f"site {site}: {known} nodes known, bias " in printed
    assert f"written: {out}" in printed
    report = tmp_path / "route"
    assert main(["evaluate-route", "--bag", str(ROUTE_BAG), "--towers", str(CAMPUS_TOWERS), "--bias-map", str(out),
                 "--out", str(report), "--quiet"]) == 0
    assert "bias map of 3 site(s)" in capsys.readouterr().out
    assert (report / "route.json").exists()


@pytest.mark.parametrize("command", ["evaluate-route", "replay", "evaluate-routes"])
def test_a_bad_bias_map_is_refused_naming_it_before_any_replay(tmp_path, capsys, command) -> None:
    bad = tmp_path / "bad.npz"
    bad.write_text("not a map")
    out = tmp_path / "out"
    bag = ["--in" if command == "replay" else "--bag", str(ROUTE_BAG)]
    assert main([command, *bag, "--towers", str(CAMPUS_TOWERS), "--bias-map", str(bad), "--out", str(out),
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"bias map {str(bad)!r} cannot be read: not a DeepSync bias map" in err and "Traceback" not in err
    assert not out.exists()


def test_a_map_of_another_frame_or_without_fusion_is_refused_by_replay(tmp_path, capsys) -> None:
    wrong = save_bias_map(small_map(ELSEWHERE), tmp_path / "elsewhere.npz")
    out = tmp_path / "out"
    assert main(["replay", "--in", str(ROUTE_BAG), "--towers", str(CAMPUS_TOWERS), "--bias-map", str(wrong),
                 "--out", str(out), "--quiet"]) == 2
    assert "was made in the frame at" in capsys.readouterr().err and not out.exists()
    assert main(["replay", "--in", str(ROUTE_BAG), "--towers", str(CAMPUS_TOWERS), "--bias-map", str(wrong),
                 "--stages", "sync,timing", "--out", str(out), "--quiet"]) == 2
    assert "a bias map corrects fusion, which this replay does not run" in capsys.readouterr().err


def test_survey_map_refuses_a_bag_without_ground_truth(tmp_path, capsys) -> None:
    bag = envelope_only_bag(tmp_path / "no_truth")
    out = tmp_path / "map.npz"
    assert main(["survey-map", "--bag", str(bag), "--towers", str(CAMPUS_TOWERS), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "no ground truth" in err and "surveying" in err and "Traceback" not in err
    assert not out.exists()


def test_the_bias_map_parameter_loads_a_map_for_fusion_or_names_what_is_wrong(tmp_path) -> None:
    campus = load_tower_database(CAMPUS_TOWERS)
    frame = Anchors(campus).frame
    made = BiasMap((frame.latitude_deg, frame.longitude_deg, frame.height_m), small_map().sites, "campus test")
    good = save_bias_map(made, tmp_path / "campus.npz")
    for node in ("tdoa_fusion", "deepsync_pipeline"):
        values = params.checked(params.NODES[node], {"bias_map": str(good)}, node)
        assert params.bias_map(values, node, campus).made_by == "campus test"
        assert params.bias_map(params.checked(params.NODES[node], {}, node), node, campus) is None  # "": none
    wrong = save_bias_map(small_map(ELSEWHERE), tmp_path / "elsewhere.npz")
    with pytest.raises(ParameterError, match=r"^tdoa_fusion\.bias_map: bias map \(a test\) was made in the frame"):
        params.bias_map({"bias_map": str(wrong)}, "tdoa_fusion", campus)
    with pytest.raises(ParameterError, match=r"^tdoa_fusion\.bias_map: no such file 'gone\.npz'$"):
        params.bias_map({"bias_map": "gone.npz"}, "tdoa_fusion", campus)
    broken = tmp_path / "broken.npz"
    broken.write_text("x")
    with pytest.raises(ParameterError, match=r"^deepsync_pipeline\.bias_map: bias map .*broken\.npz.* not a DeepSync"):
        params.bias_map({"bias_map": str(broken)}, "deepsync_pipeline", campus)
    with pytest.raises(ParameterError, match=r"^deepsync_pipeline\.bias_map: .*no fusion without a tower database"):
        params.bias_map({"bias_map": str(good)}, "deepsync_pipeline", None)
    with pytest.raises(ParameterError, match="expected a string"):
        params.checked(params.TDOA_FUSION, {"bias_map": 3}, "tdoa_fusion")


def test_a_map_from_points_averages_each_sites_biases_where_it_has_them() -> None:
    points = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    made = bias_map_from_points({"A": (points, np.array([40.0, 40.0, 40.0, 40.0])),
                                 "B": (points[:1], np.array([-5.0])), "C": (points[:0], np.empty(0))},
                                ORIGIN_TUPLE, SurveyConfig(step_m=5.0, smoothing_m=8.0, min_weight=0.5))
    assert set(made.sites) == {"A", "B"}  # a site without a point is left out
    assert made.sites["A"].at(5.0, 5.0)[0] == pytest.approx(40.0)
    assert made.sites["B"].at(0.0, 0.0)[0] == pytest.approx(-5.0)
    assert made.sites["B"].at(10.0, 10.0) is None  # 14 m: beyond a kernel sigma of its one point
    with pytest.raises(ValueError, match="at least one site"):
        bias_map_from_points({"A": (points[:0], np.empty(0))}, ORIGIN_TUPLE)
