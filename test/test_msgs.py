"""deepsync_msgs: every .msg parses the way ``rosidl_generate_interfaces`` parses it.

ROS 2 is not installable here, but Debian's ``python3-rosidl`` carries the same ``rosidl_adapter``
(.msg -> .idl) and ``rosidl_parser`` (.idl) a colcon build runs, so a malformed definition fails
this test instead of a robot's build. Runs under Debian's /usr/bin/python3, not the venv.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest
from deepsync.bag.msgdefs import MSG_NAMES, load_typestore, msgtype
from system_python import missing, run_python

REPO = Path(__file__).resolve().parents[1]
MSGS_PKG = REPO / "src" / "deepsync_msgs"

# Parses every <pkg_dir>/msg/*.msg like rosidl_generate_interfaces: rosidl_adapter's .msg parser,
# then .msg -> .idl conversion and rosidl_parser on the .idl. Prints one JSON document; any
# problem goes to stderr naming the file, with exit status 1.
PARSE_SCRIPT = r"""
import contextlib, json, sys, tempfile, traceback
from pathlib import Path
from rosidl_adapter.parser import parse_message_file
from rosidl_adapter.msg import convert_msg_to_idl
from rosidl_parser.definition import IdlLocator, Message
from rosidl_parser.parser import parse_idl_file

pkg_dir = Path(sys.argv[1]).resolve()
pkg = pkg_dir.name
result = {}
failed = False
with tempfile.TemporaryDirectory() as out, contextlib.redirect_stdout(sys.stderr):
    for path in sorted((pkg_dir / "msg").glob("*.msg")):
        try:
            spec = parse_message_file(pkg, str(path))
            idl_file = convert_msg_to_idl(
                pkg_dir, pkg, Path("msg") / path.name, Path(out) / "msg")
            idl = parse_idl_file(IdlLocator(Path(out), idl_file.relative_to(out)))
            (message,) = idl.content.get_elements_of_type(Message)
            result[path.stem] = {
                "fields": [
                    {"name": f.name, "type": str(f.type),
                     "comment": "\n".join(f.annotations.get("comment", [])),
                     "unit": f.annotations.get("unit")}
                    for f in spec.fields],
                "constants": [c.name for c in spec.constants],
                "idl_struct": list(message.structure.namespaced_type.namespaced_name()),
                "idl_members": [m.name for m in message.structure.members],
            }
        except Exception:
            failed = True
            print(f"FAILED {path.name}:\n{traceback.format_exc()}", file=sys.stderr)
print(json.dumps(result))
sys.exit(1 if failed else 0)
"""


_SKIP = missing("import rosidl_adapter.msg, rosidl_parser.parser, em", "python3-rosidl rosidl-tools")
pytestmark = pytest.mark.skipif(_SKIP is not None, reason=_SKIP or "")


def run_rosidl(pkg_dir: Path) -> subprocess.CompletedProcess[str]:
    return run_python(PARSE_SCRIPT, str(pkg_dir))


@pytest.fixture(scope="module")
def parsed() -> dict[str, dict]:
    proc = run_rosidl(MSGS_PKG)
    assert proc.returncode == 0, f"rosidl rejected deepsync_msgs:\n{proc.stderr}"
    return json.loads(proc.stdout)


def field_types(parsed: dict, name: str) -> dict[str, str]:
    return {f["name"]: f["type"] for f in parsed[name]["fields"]}


def test_message_files_match_cmake_and_core(parsed: dict) -> None:
    """The .msg files, the CMake list and the core's typestore agree on the set of messages."""
    on_disk = {p.stem for p in (MSGS_PKG / "msg").glob("*.msg")}
    cmake = (MSGS_PKG / "CMakeLists.txt").read_text()
    in_cmake = set(re.findall(r'"msg/(\w+)\.msg"', cmake))
    assert on_disk == set(parsed) == in_cmake == set(MSG_NAMES)


def test_every_message_starts_with_header(parsed: dict) -> None:
    for name, msg in parsed.items():
        first = msg["fields"][0]
        assert (first["type"], first["name"]) == ("std_msgs/Header", "header"), name


def test_no_byte_or_char_arrays(parsed: dict) -> None:
    for name, msg in parsed.items():
        for field in msg["fields"]:
            base = field["type"].split("[")[0]
            assert base not in {"byte", "char"}, f"{name}.{field['name']} is {field['type']}"


def test_every_field_is_documented(parsed: dict) -> None:
    """One comment per field (units in brackets become rosidl @unit annotations)."""
    for name, msg in parsed.items():
        for field in msg["fields"]:
            assert field["comment"].strip(), f"{name}.{field['name']} has no comment"


def test_field_types(parsed: dict) -> None:
    assert field_types(parsed, "EnvelopeSamples") == {
        "header": "std_msgs/Header",
        "sample_rate": "float64",
        "first_sample_index": "uint64",
        "adc_bits": "uint8",
        "volts_per_code": "float64",
        "samples": "int16[]",
    }
    assert field_types(parsed, "SyncWindow") == {
        "header": "std_msgs/Header",
        "pci": "uint16",
        "earfcn": "uint32",
        "carrier_frequency": "float64",
        "coarse_index": "uint64",
        "peak_metric": "float32",
        "snr_db": "float32",
        "n_frames": "uint16",
        "window_length": "uint16",
        "windows": "float32[]",
        "cosited_pci": "int16",
        "site_coefficients": "float32[]",
        "bandwidth_mhz": "float32",
    }
    assert field_types(parsed, "SyncWindowArray") == {
        "header": "std_msgs/Header",
        "first_sample_index": "uint64",
        "sample_rate": "float64",
        "clock_drift_ppm": "float64",
        "cells": "deepsync_msgs/SyncWindow[]",
        "frame": "float32[]",
        "frame_delay": "float64",
        "stack_frames": "uint16",
        "stack_hop_frames": "uint16",
    }
    assert field_types(parsed, "CellTiming") == {
        "header": "std_msgs/Header",
        "pci": "uint16",
        "toa": "float64",
        "toa_std": "float64",
        "snr_db": "float32",
        "earfcn": "uint32",
        "amplitude": "float32",
        "estimator": "string",
    }
    assert field_types(parsed, "CellTimingArray") == {
        "header": "std_msgs/Header",
        "first_sample_index": "uint64",
        "sample_rate": "float64",
        "clock_drift_ppm": "float64",
        "cells": "deepsync_msgs/CellTiming[]",
        "stack_frames": "uint16",
        "stack_hop_frames": "uint16",
    }


def test_units(parsed: dict) -> None:
    units = {(n, f["name"]): f["unit"] for n, m in parsed.items() for f in m["fields"]}
    assert units[("EnvelopeSamples", "sample_rate")] == "Hz"
    assert units[("SyncWindow", "carrier_frequency")] == "Hz"
    assert units[("CellTiming", "toa")] == "samples"
    assert units[("CellTiming", "toa_std")] == "samples"
    assert units[("CellTiming", "amplitude")] == "V"
    assert units[("CellTimingArray", "first_sample_index")] == "samples"
    assert units[("CellTimingArray", "clock_drift_ppm")] == "ppm"


def test_idl_round_trip(parsed: dict) -> None:
    """.msg -> .idl -> rosidl_parser keeps the struct name and every member."""
    for name, msg in parsed.items():
        assert msg["idl_struct"] == ["deepsync_msgs", "msg", name]
        assert msg["idl_members"] == [f["name"] for f in msg["fields"]]


def test_rosbags_reads_the_same_fields(parsed: dict) -> None:
    """The core's typestore (rosbags' own .msg parser) sees exactly rosidl's fields."""
    store = load_typestore(MSGS_PKG / "msg")
    for name, msg in parsed.items():
        _, fields = store.fielddefs[msgtype(name)]
        assert [f for f, _ in fields] == [f["name"] for f in msg["fields"]], name


@pytest.mark.parametrize(
    "definition",
    [
        pytest.param("std_msgs/Header header\nfloat64\n", id="missing-field-name"),
        pytest.param("std_msgs/Header header\nfloat64 Sample-Rate\n", id="bad-field-name"),
        pytest.param("std_msgs/Header header\nint16[ samples\n", id="unbalanced-bracket"),
        pytest.param("std_msgs/Header header\nuint8 LIMIT=300\n", id="constant-out-of-range"),
        pytest.param("std_msgs/Header header\nfloat64 x\nfloat64 x\n", id="duplicate-field"),
    ],
)
def test_malformed_definition_is_rejected(tmp_path: Path, definition: str) -> None:
    """The check above has teeth: a broken .msg makes the rosidl step fail, naming the file."""
    msg_dir = tmp_path / "deepsync_msgs" / "msg"
    msg_dir.mkdir(parents=True)
    (msg_dir / "Good.msg").write_text("std_msgs/Header header\nfloat64 x\n")
    (msg_dir / "Bad.msg").write_text(definition)
    proc = run_rosidl(tmp_path / "deepsync_msgs")
    assert proc.returncode != 0
    assert "FAILED Bad.msg" in proc.stderr
    assert "FAILED Good.msg" not in proc.stderr


def test_well_formed_definition_passes(tmp_path: Path) -> None:
    """Positive control for the negative test: the same harness accepts a valid message."""
    msg_dir = tmp_path / "deepsync_msgs" / "msg"
    msg_dir.mkdir(parents=True)
    (msg_dir / "Good.msg").write_text("# doc\nstd_msgs/Header header\n# x [m]\nfloat64 x\n")
    proc = run_rosidl(tmp_path / "deepsync_msgs")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["Good"]["fields"][1]["unit"] == "m"
