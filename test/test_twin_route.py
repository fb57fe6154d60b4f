"""Receiver trajectories: fixed points and constant-speed waypoint routes."""

import numpy as np
import pytest

from deepsync.geo import LocalFrame
from deepsync.twin.route import Trajectory

FRAME = LocalFrame(38.9869, -76.9426, 10.0)
SQUARE = [[0.0, 0.0, 1.5], [100.0, 0.0, 1.5], [100.0, 50.0, 1.5]]


def test_fixed_receiver():
    fixed = Trajectory.fixed(FRAME, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(fixed.position_enu(12.3), [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(fixed.velocity_enu(12.3), [0.0, 0.0, 0.0])
    assert fixed.position_enu(np.zeros((4, 2))).shape == (4, 2, 3)
    assert fixed.speed_mps == 0.0 and fixed.length_m == 0.0 and fixed.duration_s == 0.0


def test_route_positions_and_velocities():
    route = Trajectory(FRAME, SQUARE, speed_mps=2.0)
    assert route.length_m == pytest.approx(150.0)
    assert route.duration_s == pytest.approx(75.0)
    np.testing.assert_allclose(route.position_enu(0.0), SQUARE[0])
    np.testing.assert_allclose(route.position_enu(25.0), [50.0, 0.0, 1.5])
    np.testing.assert_allclose(route.position_enu(50.0), SQUARE[1])
    np.testing.assert_allclose(route.position_enu(60.0), [100.0, 20.0, 1.5])
    np.testing.assert_allclose(route.velocity_enu(10.0), [2.0, 0.0, 0.0])
    np.testing.assert_allclose(route.velocity_enu(60.0), [0.0, 2.0, 0.0])
    # before the start and after the end the receiver stands still at the ends
    np.testing.assert_allclose(route.position_enu(-5.0), SQUARE[0])
    np.testing.assert_allclose(route.velocity_enu(-5.0), 0.0)
    np.testing.assert_allclose(route.position_enu(1000.0), SQUARE[2])
    np.testing.assert_allclose(route.velocity_enu(1000.0), 0.0)


def test_route_is_vectorized_and_continuous():
    route = Trajectory(FRAME, SQUARE, speed_mps=1.4)
    t = np.linspace(0.0, route.duration_s, 2001)
    positions = route.position_enu(t)
    assert positions.shape == (2001, 3)
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    assert np.all(steps <= 1.4 * (t[1] - t[0]) + 1e-9)
    speeds = np.linalg.norm(route.velocity_enu(t[:-1]), axis=1)
    np.testing.assert_allclose(speeds, 1.4)


def test_looping_route_returns_to_the_start():
    route = Trajectory(FRAME, SQUARE, speed_mps=1.0, loop=True)
    closing = np.hypot(100.0, 50.0)
    assert route.length_m == pytest.approx(150.0 + closing)
    np.testing.assert_allclose(route.position_enu(route.duration_s), SQUARE[0], atol=1e-9)
    np.testing.assert_allclose(route.position_enu(route.duration_s + 25.0), [25.0, 0.0, 1.5])
    np.testing.assert_allclose(route.velocity_enu(route.duration_s - 1.0),
                               [-100.0 / closing, -50.0 / closing, 0.0])


def test_repeated_waypoints_are_skipped():
    route = Trajectory(FRAME, [SQUARE[0], SQUARE[1], SQUARE[1], SQUARE[2]], speed_mps=1.0)
    np.testing.assert_allclose(route.position_enu(100.0), SQUARE[1])
    np.testing.assert_allclose(route.velocity_enu(100.0), [0.0, 1.0, 0.0])
    np.testing.assert_allclose(route.position_enu(120.0), [100.0, 20.0, 1.5])


def test_position_llh_matches_the_frame():
    route = Trajectory(FRAME, SQUARE, speed_mps=2.0)
    lat, lon, h = route.position_llh([0.0, 50.0])
    np.testing.assert_allclose(FRAME.geodetic_to_enu(lat, lon, h), [SQUARE[0], SQUARE[1]],
                               atol=1e-6)


@pytest.mark.parametrize(("points", "speed", "message"), [
    (SQUARE, 0.0, "positive"),
    ([SQUARE[0], SQUARE[0]], 1.0, "positive length"),
    (SQUARE, -1.0, "speed_mps"),
    ([[0.0, np.nan, 0.0], SQUARE[1]], 1.0, "NaN"),
])
def test_invalid_routes(points, speed, message):
    with pytest.raises(ValueError, match=message):
        Trajectory(FRAME, points, speed_mps=speed)
