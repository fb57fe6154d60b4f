"""WGS84 geodetic <-> ECEF <-> local ENU (map frame)."""

import numpy as np
import pytest
from pyproj import Geod

from deepsync.geo import LocalFrame, ecef_to_geodetic, geodetic_to_ecef

GEOD = Geod(ellps="WGS84")
FRAME = LocalFrame(38.98690, -76.94260, 10.0)


def test_ecef_of_reference_points():
    np.testing.assert_allclose(geodetic_to_ecef(0.0, 0.0, 0.0), [6378137.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(0.0, 90.0, 100.0), [0.0, 6378237.0, 0.0],
                               atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(90.0, 0.0, 0.0), [0.0, 0.0, 6356752.314245],
                               atol=1e-5)


def test_geodetic_ecef_round_trip_vectorized():
    rng = np.random.default_rng(1)
    lat = rng.uniform(-89, 89, (4, 5))
    lon = rng.uniform(-180, 180, (4, 5))
    h = rng.uniform(-100, 9000, (4, 5))
    ecef = geodetic_to_ecef(lat, lon, h)
    assert ecef.shape == (4, 5, 3)
    lat2, lon2, h2 = ecef_to_geodetic(ecef)
    np.testing.assert_allclose(lat2, lat, atol=1e-9)
    np.testing.assert_allclose(lon2, lon, atol=1e-9)
    np.testing.assert_allclose(h2, h, atol=1e-4)


def test_origin_is_zero_and_scalar_shapes():
    np.testing.assert_allclose(FRAME.geodetic_to_enu(38.98690, -76.94260, 10.0), 0.0, atol=1e-6)
    assert FRAME.geodetic_to_enu(38.99, -76.94, 10.0).shape == (3,)
    lat, lon, h = FRAME.enu_to_geodetic([0.0, 0.0, 0.0])
    assert (float(lat), float(lon), float(h)) == pytest.approx((38.98690, -76.94260, 10.0))


def test_enu_round_trip_below_a_millimetre():
    rng = np.random.default_rng(2)
    enu = rng.uniform(-20_000, 20_000, (200, 3))
    enu[:, 2] = rng.uniform(-50, 500, 200)
    lat, lon, h = FRAME.enu_to_geodetic(enu)
    back = FRAME.geodetic_to_enu(lat, lon, h)
    assert np.max(np.linalg.norm(back - enu, axis=-1)) < 1e-3


def test_one_km_north_sits_below_the_tangent_plane():
    lon, lat, _ = GEOD.fwd(FRAME.longitude_deg, FRAME.latitude_deg, 0.0, 1000.0)
    east, north, up = FRAME.geodetic_to_enu(lat, lon, FRAME.height_m)
    assert abs(east) < 1e-6
    assert north == pytest.approx(1000.0, abs=0.01)
    # Earth curvature: d^2 / (2 R) with the meridian radius of curvature, ~6.36e6 m here.
    assert up == pytest.approx(-1000.0**2 / (2 * 6.36e6), abs=0.002)


def test_east_axis_points_east_and_up_is_up():
    lon, lat, _ = GEOD.fwd(FRAME.longitude_deg, FRAME.latitude_deg, 90.0, 200.0)
    east, north, up = FRAME.geodetic_to_enu(lat, lon, FRAME.height_m + 30.0)
    assert east == pytest.approx(200.0, abs=0.01)
    assert abs(north) < 0.01
    assert up == pytest.approx(30.0, abs=0.01)


@pytest.mark.parametrize("azimuth", [0.0, 37.0, 90.0, 200.0, 311.0])
@pytest.mark.parametrize("distance", [100.0, 1000.0, 5000.0])
def test_distances_agree_with_geodesic(azimuth, distance):
    lon1, lat1, _ = GEOD.fwd(FRAME.longitude_deg, FRAME.latitude_deg, azimuth + 90, 700.0)
    lon2, lat2, _ = GEOD.fwd(lon1, lat1, azimuth, distance)
    a, b = FRAME.geodetic_to_enu([lat1, lat2], [lon1, lon2], 0.0)
    # The ENU distance is the chord, shorter than the arc by d^3 / (24 R^2): < 0.2 mm at 5 km.
    assert np.linalg.norm(b - a) == pytest.approx(GEOD.inv(lon1, lat1, lon2, lat2)[2], abs=1e-3)


def test_ecef_enu_inverse():
    points = FRAME.enu_to_ecef([[100.0, -50.0, 3.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(FRAME.ecef_to_enu(points), [[100.0, -50.0, 3.0], [0, 0, 0]],
                               atol=1e-8)


@pytest.mark.parametrize(("lat", "lon", "message"), [(91.0, 0.0, "latitude"),
                                                      (0.0, 181.0, "longitude"),
                                                      (float("nan"), 0.0, "finite")])
def test_frame_rejects_bad_origin(lat, lon, message):
    with pytest.raises(ValueError, match=message):
        LocalFrame(lat, lon)


def test_points_need_three_coordinates():
    with pytest.raises(ValueError, match="length 3"):
        FRAME.enu_to_geodetic([1.0, 2.0])
