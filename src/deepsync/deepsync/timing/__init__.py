"""Sub-sample timing of detected cells: classical estimators with an honest 1-sigma, the Cramer-Rao bound, the timing stage."""

# torch's CPU wheel, as pinned by constraints.txt (run from the repository root): a torch from
# PyPI brings several GB of CUDA that a tracker or a robot's CPU never uses
TORCH_INSTALL = "pip install -c constraints.txt torch --index-url https://download.pytorch.org/whl/cpu"


def network_install_hint(module: str) -> str:
    """How to install ``module``, missing for the timing network (the stage's network estimators,
    ``deepsync train``): torch's CPU wheel, or the package's network extra."""
    return TORCH_INSTALL if module == "torch" else "pip install -e 'src/deepsync[network]'"
