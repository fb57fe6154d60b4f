"""The core's shape, checked from its source: one-way imports, stages chained in one place, one
copy of each shared helper and constant. A violation fails here, not in a later review."""

import ast
import re
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parents[1] / "src" / "deepsync" / "deepsync"
LAYERS = ["types", "lte", "frontend", "sync", "timing", "fusion"]  # each may import only those before it
STAGES = ["sync", "timing", "fusion"]


def modules() -> dict[str, Path]:
    """Dotted name below ``deepsync`` -> file, for every module of the core."""
    return {".".join(p.relative_to(CORE).with_suffix("").parts): p for p in sorted(CORE.rglob("*.py"))}


def imports(path: Path) -> set[str]:
    """Every module a file imports (absolute names; relative imports resolved)."""
    package = ["deepsync", *path.relative_to(CORE).parent.parts]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join([*base, *(node.module.split(".") if node.module else [])])
            found.add(module)
            found |= {f"{module}.{alias.name}" for alias in node.names}
    return found


def top(name: str) -> str | None:
    """The part of the core a dotted module name belongs to (``deepsync.sync.search`` -> sync)."""
    parts = name.split(".")
    return parts[1] if parts[0] == "deepsync" and len(parts) > 1 else None


@pytest.mark.parametrize("name, path", sorted(modules().items()))
def test_imports_run_one_way(name, path):
    own = name.split(".")[0]
    used = {top(m) for m in imports(path)} - {None, own}
    if own in LAYERS:
        later = set(LAYERS[LAYERS.index(own) + 1 :])
        assert not used & later, f"{name} imports {sorted(used & later)}, which build on it"
    if own == "types":
        assert not used, f"types imports {sorted(used)}: it must import nothing of the project"
    if own in STAGES:
        forbidden = {"bag", "sources", "pipeline", "cli", "recording", "twin", "testing", "eval"}
        assert not used & forbidden, f"stage module {name} imports {sorted(used & forbidden)}"
    if own not in ("timing", "training"):  # the network, and the making of it
        assert not any(m == "torch" or m.startswith("torch.") for m in imports(path)), f"{name} imports torch"


def test_only_the_pipeline_chains_stages():
    chaining = [name for name, path in modules().items()
                if {"deepsync.sync.stage", "deepsync.timing.stage"} <= imports(path)]
    assert chaining == ["pipeline"]


def test_sync_holds_only_the_cell_search():
    assert sorted(p.stem for p in (CORE / "sync").glob("*.py")) == [
        "__init__", "bandwidths", "correlation", "search", "sites", "stacking", "stage", "windows"]


@pytest.mark.parametrize("pattern, home", [
    (r"1\.4826", "numeric.py"),  # the MAD -> sigma factor
    (r"299_?792_?458", "types.py"),  # light speed
    (r"^FRAME_SECONDS\s*=", "types.py"),
    (r"^HALF_FRAME_SECONDS\s*=", "types.py"),
    (r"0\.5 \* \(\w+ - \w+\) / \w+", "numeric.py"),  # a parabola's vertex
])
def test_shared_helpers_and_constants_live_in_one_place(pattern, home):
    where = [str(p.relative_to(CORE)) for p in CORE.rglob("*.py") if re.search(pattern, p.read_text(), re.M)]
    assert where == [home]


# -- the timing estimators: one registry (deepsync.timing.registry) ------------------------------

ROS_BINDING = CORE.parents[2] / "deepsync_ros" / "deepsync_ros"
# the registry, and the estimator functions' own labels of what they return
ESTIMATOR_HOMES = {"timing/registry.py", "timing/estimators.py"}


def test_estimator_names_are_written_only_in_the_registry():
    """An estimator's name in a branch, a list of choices or a table's columns anywhere else is
    a place that adding or renaming one would miss."""
    from deepsync.timing.registry import ESTIMATORS

    where = []
    for root in (CORE, ROS_BINDING):
        for path in sorted(root.rglob("*.py")):
            if root is CORE and path.relative_to(CORE).as_posix() in ESTIMATOR_HOMES:
                continue
            where += [f"{path.relative_to(root.parent)}:{node.lineno} {node.value!r}"
                      for node in ast.walk(ast.parse(path.read_text()))
                      if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in ESTIMATORS]
    assert not where, f"estimator names outside timing/registry.py: {where}"


def test_the_timing_stage_names_no_estimator():
    """The stage dispatches on what an estimator times a cell from (``Input``) and calls its
    functions; it never singles one out (no ``Estimator.X``, no registry lookup, no ``==``)."""
    tree = ast.parse((CORE / "timing" / "stage.py").read_text())
    from_registry = {alias.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                     and node.module == "deepsync.timing.registry" for alias in node.names}
    # ESTIMATORS: the whole registry, as TimingConfig.estimator's choices (deepsync.schema)
    assert from_registry <= {"DEFAULT", "ESTIMATORS", "Estimator", "Input"}, from_registry
    singled_out = [ast.unparse(node) for node in ast.walk(tree)
                   if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                   and node.value.id == "Estimator" and node.attr != "names"]
    assert not singled_out, singled_out
    compared = [ast.unparse(node) for node in ast.walk(tree) if isinstance(node, ast.Compare)
                and "estimator" in ast.unparse(node) and "estimator.input" not in ast.unparse(node)]
    assert not compared, compared


# -- the parameter schema: a setting is written once, on its config field (deepsync.schema) ------

def test_no_node_parameter_of_a_core_setting_is_written_by_hand():
    """A node parameter named as a stage config's setting (or made from one under another name)
    takes its description, range and choices from the setting: ``from_setting``, never a
    second ``ParamSpec(...)`` with its own text and range."""
    from deepsync.motion import MOTION
    from deepsync.pipeline import setting_paths
    from deepsync_ros import params

    core = {name: described for name, (_, described) in setting_paths().items()} | {MOTION.name: MOTION}
    made = {spec.setting.name for specs in params.NODES.values() for spec in specs if spec.setting is not None}
    for node, specs in params.NODES.items():
        for spec in specs:
            if spec.name in core or spec.setting is not None:
                described = spec.setting
                assert described is core.get(described.name if described else spec.name), (
                    f"{node}.{spec.name} is written by hand: make it with params.from_setting")
                assert spec.description.startswith(described.described), f"{node}.{spec.name}"
                assert spec.choices == described.names
                if described.bounds is not None:
                    assert spec.range[1] == described.bounds[1], f"{node}.{spec.name}"
    assert made, "no node parameter is made from a core setting"


def test_no_command_line_flag_of_a_core_setting_is_written_by_hand():
    """Every flag that sets a stage config's setting is made by ``deepsync.schema.add_flag``
    (its action carries the setting): no flag repeats a range, a help text or the choices."""
    from deepsync.cli import build_parser
    from deepsync.motion import MOTION
    from deepsync.pipeline import setting_paths

    core = {name: described for name, (_, described) in setting_paths().items()} | {MOTION.name: MOTION}
    flags = {"--frames": "n_frames", "--hop": "hop_frames", "--search-every": "search_every",
             "--estimator": "estimator", "--motion": "motion", "--checkpoint": "checkpoint"}
    parser = build_parser()
    commands = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction").choices
    seen = set()
    for command, sub in commands.items():
        for action in sub._actions:
            named = [flags.get(option) or core.get(option.lstrip("-").replace("-", "_")) and
                     option.lstrip("-").replace("-", "_") for option in action.option_strings]
            named = [name for name in named if name]
            if not named or (command == "export-onnx" and named == ["checkpoint"]):
                continue  # export-onnx's checkpoint is the network exported, not the timing config's
            described = getattr(action, "setting", None)
            if described is None and command == "evaluate-timing" and named == ["n_frames"]:
                assert action.type.__name__ == "_frame_counts"  # a list of stack lengths, each the setting's
                continue
            assert described is core[named[0]], f"deepsync {command} {action.option_strings}: written by hand"
            seen.add(named[0])
    assert {"n_frames", "hop_frames", "search_every", "estimator", "motion", "multipath_std_m"} <= seen
