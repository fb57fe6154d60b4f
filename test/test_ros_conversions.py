"""deepsync_ros.conversions: core types <-> messages, as the nodes build and read them.

Without ROS, the field mapping is checked in two flavours that differ only where rclpy differs
from rosbags: rosbags' classes with numpy arrays (serialised to CDR and back, as a bag carries
them), and rosbags' classes holding the ``array.array`` s that :func:`deepsync_ros.conversions.to_array`
makes for rclpy's generated setters (what a node publishes). Both must read back as the same core
objects. Where ``rclpy`` and the built ``deepsync_msgs`` import, the same round trips run with
rclpy's own classes.
"""

from __future__ import annotations

import array
import importlib
import math

import numpy as np
import pytest

from deepsync.bag import convert, typestore
from deepsync.bag.convert import MessageTypes, rosbags_types
from deepsync.geo import LocalFrame
from deepsync.types import (
    UNMEASURED_VARIANCE,
    CellTiming,
    EnvelopeChunk,
    Fix,
    FixKind,
    StackArrivals,
    StackWindows,
    SyncWindow,
)
from deepsync_ros import conversions

STAMP_NS = 1_767_225_600_123_456_789
FRAME = LocalFrame(38.98690, -76.94260, 10.0)


def chunk() -> EnvelopeChunk:
    codes = np.random.default_rng(1).integers(-2048, 2048, 1920).astype(np.int16)
    return EnvelopeChunk(STAMP_NS, 1.92e6, 96_000, 12, 2.0 / 4096, codes)


def stack() -> StackWindows:
    rng = np.random.default_rng(2)
    windows = (
        SyncWindow(STAMP_NS, 56, 96_123, rng.normal(size=(10, 301)).astype(np.float32), 14.5, 3.25,
                   earfcn=2300, carrier_hz=2.12e9),
        SyncWindow(STAMP_NS, 120, 97_001, rng.normal(size=(10, 301)).astype(np.float32), 9.0, -1.5,
                   cosited_pci=121, site_coefficients=(1.0, 0.5, 0.25, -0.125)),
    )
    return StackWindows(STAMP_NS, 96_000, 1.92e6, windows, clock_drift_ppm=0.25,
                        frame=rng.normal(size=1920).astype(np.float32), frame_delay=0.0864)


def arrivals() -> StackArrivals:
    cells = (
        CellTiming(56, 96_123.375, 0.0625, 3.25, "ml", earfcn=2300, amplitude=0.0125),
        CellTiming(301, 97_500.5, 0.5, -1.0, "parabolic"),  # amplitude unmeasured: NaN
    )
    return StackArrivals(STAMP_NS, 96_000, 1.92e6, cells, clock_drift_ppm=None)


def fix() -> Fix:
    covariance = np.array([[25.0, 4.0, 0.0], [4.0, 36.0, 0.0], [0.0, 0.0, UNMEASURED_VARIANCE]])
    return Fix(STAMP_NS, (120.5, -340.25, 1.5), covariance, ("A", "B", "C"), FixKind.TRACKED)


# -- to_array ---------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype, code", [("<i2", "h"), ("<f4", "f"), ("<f8", "d")])
def test_to_array_keeps_type_and_values(dtype: str, code: str) -> None:
    values = np.array([-3, 0, 2, 1000], dtype=dtype)
    out = conversions.to_array(values)
    assert isinstance(out, array.array) and out.typecode == code
    assert list(out) == values.tolist()


def test_to_array_of_a_strided_view() -> None:
    values = np.arange(12, dtype="<f4").reshape(3, 4)[:, 1]
    assert list(conversions.to_array(values)) == [1.0, 5.0, 9.0]


@pytest.mark.parametrize("dtype", ["<i4", "u1", "<c8", ">i2", ">f4", "bool"])
def test_to_array_refuses_other_dtypes(dtype: str) -> None:
    with pytest.raises(ValueError, match="no ROS sequence type for numpy dtype"):
        conversions.to_array(np.zeros(3, dtype=dtype))


# -- round trips ------------------------------------------------------------------------------

def rosbags() -> MessageTypes:
    return rosbags_types(typestore())


def array_flavour() -> MessageTypes:
    """rosbags' classes holding array.array sequences, as rclpy's do."""
    return MessageTypes(typestore().types.__getitem__, conversions.to_array)


def through_cdr(message: object, msgtype: str) -> object:
    store = typestore()
    return store.deserialize_cdr(store.serialize_cdr(message, msgtype), msgtype)


def flavours() -> list:
    """(name, builder store, what the message goes through before it is read)."""
    return [("rosbags via CDR", rosbags(), through_cdr), ("array.array sequences", array_flavour(), None)]


def rebuilt(message: object, msgtype: str, carry) -> object:
    return message if carry is None else carry(message, msgtype)


def assert_same_windows(got: StackWindows, want: StackWindows) -> None:
    assert (got.stamp_ns, got.first_sample_index, got.sample_rate, got.clock_drift_ppm) == (
        want.stamp_ns, want.first_sample_index, want.sample_rate, want.clock_drift_ppm)
    np.testing.assert_array_equal(got.frame, want.frame)
    assert got.frame_delay == want.frame_delay
    assert len(got.windows) == len(want.windows)
    for a, b in zip(got.windows, want.windows):
        assert (a.stamp_ns, a.pci, a.coarse_index, a.earfcn, a.carrier_hz, a.cosited_pci) == (
            b.stamp_ns, b.pci, b.coarse_index, b.earfcn, b.carrier_hz, b.cosited_pci)
        assert a.peak_metric == pytest.approx(b.peak_metric, rel=1e-6)  # float32 fields
        assert a.snr_db == pytest.approx(b.snr_db, rel=1e-6)
        np.testing.assert_array_equal(a.windows, b.windows)
        assert a.site_coefficients == b.site_coefficients  # exact in float32


def assert_same_arrivals(got: StackArrivals, want: StackArrivals) -> None:
    assert (got.stamp_ns, got.first_sample_index, got.sample_rate, got.clock_drift_ppm) == (
        want.stamp_ns, want.first_sample_index, want.sample_rate, want.clock_drift_ppm)
    for a, b in zip(got.cells, want.cells, strict=True):
        assert (a.pci, a.toa, a.toa_std, a.estimator, a.earfcn) == (b.pci, b.toa, b.toa_std, b.estimator, b.earfcn)
        assert a.snr_db == pytest.approx(b.snr_db, rel=1e-6)
        assert (math.isnan(a.amplitude) and math.isnan(b.amplitude)) or a.amplitude == pytest.approx(b.amplitude)


@pytest.mark.parametrize("name, store, carry", flavours())
def test_envelope_round_trip(name: str, store: MessageTypes, carry) -> None:
    want = chunk()
    message = rebuilt(convert.envelope_to_msg(want, store=store), convert.ENVELOPE_SAMPLES, carry)
    assert message.header.frame_id == conversions.ENVELOPE_FRAME_ID
    got = conversions.envelope_from_msg(message)
    assert (got.stamp_ns, got.sample_rate, got.first_sample_index, got.adc_bits, got.volts_per_code) == (
        want.stamp_ns, want.sample_rate, want.first_sample_index, want.adc_bits, want.volts_per_code)
    np.testing.assert_array_equal(got.samples, want.samples)


@pytest.mark.parametrize("name, store, carry", flavours())
def test_sync_window_array_round_trip(name: str, store: MessageTypes, carry) -> None:
    want = stack()
    message = rebuilt(convert.sync_window_array_to_msg(want, frame_id="adc", store=store),
                      convert.SYNC_WINDOW_ARRAY, carry)
    assert message.header.frame_id == "adc"
    assert_same_windows(conversions.sync_window_array_from_msg(message), want)


@pytest.mark.parametrize("name, store, carry", flavours())
def test_cell_timing_array_round_trip(name: str, store: MessageTypes, carry) -> None:
    want = arrivals()
    message = rebuilt(convert.cell_timing_array_to_msg(want, store=store), convert.CELL_TIMING_ARRAY, carry)
    assert_same_arrivals(conversions.cell_timing_array_from_msg(message), want)


@pytest.mark.parametrize("name, store, carry", flavours())
def test_pose_round_trip(name: str, store: MessageTypes, carry) -> None:
    want = fix()
    message = rebuilt(convert.fix_to_pose_msg(want, store=store), convert.POSE_WITH_COVARIANCE_STAMPED, carry)
    assert conversions.stamp_to_ns(message.header.stamp) == want.stamp_ns
    assert message.header.frame_id == conversions.MAP_FRAME_ID
    assert conversions.position_from_pose_msg(message) == want.position_enu
    covariance = np.asarray(message.pose.covariance).reshape(6, 6)
    np.testing.assert_array_equal(covariance[:3, :3], want.covariance)
    np.testing.assert_array_equal(np.diag(covariance)[3:], UNMEASURED_VARIANCE)


@pytest.mark.parametrize("name, store, carry", flavours())
def test_an_initial_pose_becomes_a_prior_with_its_position_covariance(name: str, store: MessageTypes, carry) -> None:
    want = fix()
    message = rebuilt(convert.fix_to_pose_msg(want, store=store), convert.POSE_WITH_COVARIANCE_STAMPED, carry)
    prior = conversions.prior_from_pose_msg(message)
    assert prior.position_enu == want.position_enu
    np.testing.assert_array_equal(prior.covariance, want.covariance)


def initial_pose(covariance: np.ndarray) -> object:
    """An initial pose as RViz's "2D Pose Estimate" sends it: x, y (and yaw) variances, z none."""
    message = convert.fix_to_pose_msg(Fix(STAMP_NS, (10.0, 20.0, 0.0), np.eye(3), ()), store=rosbags())
    full = np.zeros((6, 6))
    full[:3, :3] = covariance
    full[5, 5] = 0.068
    message.pose.covariance = full.ravel()
    return message


def test_an_initial_pose_without_a_z_variance_leaves_up_unmeasured() -> None:
    prior = conversions.prior_from_pose_msg(initial_pose(np.diag([0.25, 0.25, 0.0])))
    np.testing.assert_array_equal(prior.covariance, np.diag([0.25, 0.25, UNMEASURED_VARIANCE]))


def test_an_initial_pose_faces_its_yaw_where_the_yaw_has_a_variance() -> None:
    message = initial_pose(np.diag([0.25, 0.25, 0.0]))
    message.pose.pose.orientation.z, message.pose.pose.orientation.w = math.sin(0.6), math.cos(0.6)
    prior = conversions.prior_from_pose_msg(message)
    assert prior.heading_rad == pytest.approx(1.2) and prior.heading_std_rad == pytest.approx(math.sqrt(0.068))
    assert prior.widened(10.0).heading_rad == prior.heading_rad  # widening the position keeps it
    full = np.asarray(message.pose.covariance, dtype=np.float64).reshape(6, 6).copy()
    full[5, 5] = 0.0  # no yaw variance: the yaw is not a heading anyone claims
    message.pose.covariance = full.ravel()
    assert conversions.prior_from_pose_msg(message).heading_rad is None


@pytest.mark.parametrize("covariance, match", [
    (np.diag([0.0, 0.25, 0.0]), "x and y need a variance"), (np.diag([0.25, math.nan, 0.0]), "not finite"),
    (np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "positive definite")])
def test_an_initial_pose_without_a_usable_covariance_is_refused(covariance: np.ndarray, match: str) -> None:
    with pytest.raises(ValueError, match=f"initial pose: .*{match}"):
        conversions.prior_from_pose_msg(initial_pose(covariance))


@pytest.mark.parametrize("name, store, carry", flavours())
def test_navsat_round_trip(name: str, store: MessageTypes, carry) -> None:
    want = fix()
    message = rebuilt(convert.fix_to_navsat_msg(want, FRAME, store=store), convert.NAV_SAT_FIX, carry)
    assert message.header.frame_id == conversions.ANTENNA_FRAME_ID
    east, north, up = FRAME.geodetic_to_enu(message.latitude, message.longitude, message.altitude)
    np.testing.assert_allclose([east, north, up], want.position_enu, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(message.position_covariance).reshape(3, 3), want.covariance)


@pytest.mark.parametrize("name, store, carry", flavours())
def test_a_stack_without_a_fix_is_a_navsat_saying_no_fix(name: str, store: MessageTypes, carry) -> None:
    """As a GNSS driver says it: STATUS_NO_FIX, covariance UNKNOWN, no position; and our own GNSS
    reader skips it, as it does a receiver's."""
    message = rebuilt(convert.no_fix_to_navsat_msg(1_767_225_600_400_000_000, store=store), convert.NAV_SAT_FIX,
                      carry)
    assert message.status.status == convert.NAV_SAT_STATUS_NO_FIX == -1
    assert message.position_covariance_type == convert.NAV_SAT_COVARIANCE_UNKNOWN == 0
    assert math.isnan(message.latitude) and math.isnan(message.longitude)
    assert conversions.stamp_to_ns(message.header.stamp) == 1_767_225_600_400_000_000
    assert message.header.frame_id == conversions.ANTENNA_FRAME_ID
    assert convert.gnss_fix_from_msg(message) is None


def test_a_window_array_of_the_wrong_size_is_a_value_error() -> None:
    message = convert.sync_window_array_to_msg(stack(), store=array_flavour())
    message.cells[0].windows = conversions.to_array(np.zeros(3, dtype="<f4"))
    with pytest.raises(ValueError, match="3 window values, but n_frames x window_length = 10 x 301"):
        conversions.sync_window_array_from_msg(message)


def test_a_nan_arrival_is_a_value_error() -> None:
    message = convert.cell_timing_array_to_msg(arrivals(), store=array_flavour())
    message.cells[1].toa = math.nan
    with pytest.raises(ValueError, match="CellTiming.toa nan must be finite"):
        conversions.cell_timing_array_from_msg(message)


# -- with rclpy's own classes -----------------------------------------------------------------

def _ros_missing() -> str | None:
    for module in ("rclpy", "deepsync_msgs.msg", "geometry_msgs.msg", "sensor_msgs.msg"):
        try:
            importlib.import_module(module)
        except ImportError as error:
            return (f"{module} does not import ({error}): the rclpy round trips need ROS 2 Jazzy sourced "
                    "and the workspace built (colcon build; source install/setup.bash)")
    return None


_MISSING = _ros_missing()
needs_ros = pytest.mark.skipif(_MISSING is not None, reason=str(_MISSING))


@needs_ros
def test_rclpy_envelope_round_trip() -> None:
    want = chunk()
    message = conversions.envelope_to_msg(want, frame_id="adc")
    assert type(message) is conversions.message_class("deepsync_msgs/msg/EnvelopeSamples")
    assert message.header.frame_id == "adc"
    got = conversions.envelope_from_msg(message)
    assert (got.stamp_ns, got.first_sample_index, got.adc_bits) == (want.stamp_ns, want.first_sample_index,
                                                                     want.adc_bits)
    np.testing.assert_array_equal(got.samples, want.samples)


@needs_ros
def test_rclpy_sync_window_array_round_trip() -> None:
    want = stack()
    assert_same_windows(conversions.sync_window_array_from_msg(conversions.sync_window_array_to_msg(want)), want)


@needs_ros
def test_rclpy_cell_timing_array_round_trip() -> None:
    want = arrivals()
    assert_same_arrivals(conversions.cell_timing_array_from_msg(conversions.cell_timing_array_to_msg(want)), want)


@needs_ros
def test_rclpy_fix_messages() -> None:
    want = fix()
    pose = conversions.fix_to_pose_msg(want, frame_id="map")
    assert conversions.position_from_pose_msg(pose) == want.position_enu
    np.testing.assert_array_equal(np.asarray(pose.pose.covariance).reshape(6, 6)[:3, :3], want.covariance)
    navsat = conversions.fix_to_navsat_msg(want, FRAME)
    east, north, up = FRAME.geodetic_to_enu(navsat.latitude, navsat.longitude, navsat.altitude)
    np.testing.assert_allclose([east, north, up], want.position_enu, atol=1e-6)
