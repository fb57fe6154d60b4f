"""Sionna RT, imported on demand: the optional extra ``deepsync[raytrace]``.

Dr.Jit (under Mitsuba and Sionna) runs on the CPU through LLVM and loads whatever
``libLLVM`` it finds first; the LLVM 14 and 15 of Debian bookworm crash it, LLVM 19 works. So
before the first import this points ``DRJIT_LIBLLVM_PATH`` at Debian's ``libllvm19`` where
that package is installed and the user has not chosen a library of their own.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from types import ModuleType

LLVM_LIBRARY = Path("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")  # Debian's libllvm19
INSTALL_HINT = ("install the optional extra: pip install -c constraints.txt -e 'src/deepsync[raytrace]' "
                "(sionna-rt, shapely, trimesh, mapbox-earcut; scripts/setup.sh does it) and Debian's libllvm19 "
                "(scripts/debian_packages.sh), or set DRJIT_LIBLLVM_PATH to an LLVM >= 16 library")


class RayTracingUnavailable(RuntimeError):
    """Sionna RT (or the LLVM it runs on) is not installed; the message says what to install."""


def point_drjit_at_llvm() -> None:
    """Set ``DRJIT_LIBLLVM_PATH`` to Debian's LLVM 19 when it is unset and that library exists
    (it must be set before drjit is first imported)."""
    if "DRJIT_LIBLLVM_PATH" not in os.environ and LLVM_LIBRARY.is_file():
        os.environ["DRJIT_LIBLLVM_PATH"] = str(LLVM_LIBRARY)


def missing() -> str | None:
    """Why ray tracing cannot run here (a sentence naming what to install), or None."""
    for module in ("sionna", "shapely", "trimesh", "mapbox_earcut"):
        try:
            found = importlib.util.find_spec(module) is not None
        except (ImportError, ValueError):  # a broken or blocked installation
            found = False
        if not found:
            return f"{module} is not installed: {INSTALL_HINT}"
    point_drjit_at_llvm()
    library = os.environ.get("DRJIT_LIBLLVM_PATH")
    if library is None:
        return f"no LLVM library for Dr.Jit: {INSTALL_HINT}"
    if not Path(library).is_file():
        return f"DRJIT_LIBLLVM_PATH names {library}, which does not exist: {INSTALL_HINT}"
    return None


def sionna_rt() -> ModuleType:
    """The ``sionna.rt`` module, LLVM set up first; RayTracingUnavailable saying what to
    install when it cannot be had."""
    reason = missing()
    if reason is not None:
        raise RayTracingUnavailable(f"ray tracing is unavailable: {reason}")
    import sionna.rt  # noqa: PLC0415 (optional, heavy: imported on first use)

    return sionna.rt
