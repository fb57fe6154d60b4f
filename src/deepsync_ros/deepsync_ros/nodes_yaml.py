"""The nodes' parameters file (``config/deepsync_nodes.yaml``), written from their specs.

Every parameter at its default, each explained once (where it first appears) by its spec's own
description and constraints, the very text ``ros2 param describe`` shows: the file repeats no
help by hand, and ``test/test_ros_params.py`` checks it is what this module writes. After a
parameter changes, rewrite it from the repository's root::

    PYTHONPATH=src/deepsync:src/deepsync_ros python -m deepsync_ros.nodes_yaml > src/deepsync_ros/config/deepsync_nodes.yaml

Pure Python (no rclpy).
"""

from __future__ import annotations

import textwrap

import yaml

from .params import NODES, ParamSpec, ParamValue

HEADER = """\
Parameters of the DeepSync nodes (deepsync_ros), every one of them, at its default. Written from
the nodes' parameter specs by `python -m deepsync_ros.nodes_yaml` (do not edit by hand: a test
compares); each parameter is explained where it first appears, as `ros2 param describe <node>
<name>` explains it. The launch file passes this file to each node and overrides the paths
(source, towers, frontend), which stay "" here; with those set to bags/campus and
config/towers/campus.yaml, these values run the bundled campus bag. Numbers keep their type:
write 2.0, not 2, for a double (rclpy refuses an integer for a double parameter). Parameters
marked "runtime" may be set while the node runs (`ros2 param set`); the others configure a stage
built once. Keys are /**/<node name>: a plain name would reach a node in the root namespace
only, and the launch file runs the nodes in /deepsync (or any namespace it is given)."""
PIPELINE_NOTE = """\
The whole chain in one process: envelope_adc's source parameters, then cell_sync's,
cell_timing's and tdoa_fusion's (same meanings). The front end is the recording's own."""
WIDTH = 100


def _comment(text: str, indent: str) -> list[str]:
    return textwrap.wrap(text, WIDTH - len(indent) - 2, initial_indent=f"{indent}# ", subsequent_indent=f"{indent}# ",
                         break_on_hyphens=False)


def _value(value: ParamValue) -> str:
    return yaml.safe_dump(value, default_flow_style=True).removesuffix("\n...\n").strip()


def explained(spec: ParamSpec) -> str:
    """A parameter's help as the file gives it: "runtime." where it may change while the node
    runs, its description, its constraints."""
    text = ("runtime. " if not spec.read_only else "") + spec.description
    return f"{text} Allowed: {spec.constraints}." if spec.constraints else text


def nodes_yaml() -> str:
    """The whole file."""
    lines = _comment(HEADER, "")
    seen: set[tuple[str, str]] = set()  # (name, description) already explained
    for node, specs in NODES.items():
        lines.append("")
        if node == "deepsync_pipeline":
            lines += _comment(PIPELINE_NOTE, "")
        lines += [f"/**/{node}:", "  ros__parameters:"]
        for spec in specs:
            key = (spec.name, explained(spec))
            if key not in seen:
                lines += _comment(key[1], "    ")
                seen.add(key)
            lines.append(f"    {spec.name}: {_value(spec.default)}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(nodes_yaml(), end="")
