import os
from glob import glob

from setuptools import find_packages, setup

package_name = "deepsync_ros"

# The launch file's defaults (parameters, tower database, the bundled bag) and the example
# configs live at the repository root, two levels above this file. colcon runs setup.py with
# the package directory as the working directory for a plain build, but from its build
# directory (build/deepsync_ros, holding a symlink to this file) for --symlink-install; colcon
# also insists that data_files sources are relative paths. So every source is written relative
# to the current working directory, starting from where this file really is.
HERE = os.path.dirname(os.path.realpath(__file__))
REPO = os.path.normpath(os.path.join(HERE, "..", ".."))
SHARE = os.path.join("share", package_name)


def from_here(*parts: str) -> str:
    """A path inside this package, relative to the working directory."""
    return os.path.relpath(os.path.join(HERE, *parts))


def from_repo(*parts: str) -> str:
    """A path at the repository root, relative to the working directory."""
    return os.path.relpath(os.path.join(REPO, *parts))


setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(where=HERE, exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [from_here("resource", package_name)]),
        (SHARE, [from_here("package.xml")]),
        (os.path.join(SHARE, "launch"), sorted(glob(from_here("launch", "*.launch.py")))),
        (
            os.path.join(SHARE, "config"),
            [
                from_repo("config", "deepsync_nodes.yaml"),
                from_repo("config", "robot_localization_ekf.yaml"),
                from_repo("config", "foxglove_layout.json"),
            ],
        ),
        (os.path.join(SHARE, "config", "towers"), [from_repo("config", "towers", "campus.yaml")]),
        (
            os.path.join(SHARE, "bags", "campus"),
            [from_repo("bags", "campus", "metadata.yaml"), from_repo("bags", "campus", "campus.mcap")],
        ),
    ],
    python_requires=">=3.10",
    # Only what pip can provide. rclpy, the message packages and deepsync_msgs come from ROS
    # (package.xml); the numerical stack comes from the deepsync core package.
    install_requires=["setuptools", "deepsync", "numpy>=1.24,<2"],
    zip_safe=True,
    maintainer="DeepSync",
    maintainer_email="dev@deepsync.invalid",
    description="ROS 2 binding of DeepSync: rclpy nodes, launch files, conversions and bag replay.",
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},
    entry_points={
        "console_scripts": [
            "envelope_adc = deepsync_ros.entry:envelope_adc",
            "cell_sync = deepsync_ros.entry:cell_sync",
            "cell_timing = deepsync_ros.entry:cell_timing",
            "tdoa_fusion = deepsync_ros.entry:tdoa_fusion",
            "deepsync_pipeline = deepsync_ros.entry:deepsync_pipeline",
        ]
    },
)
