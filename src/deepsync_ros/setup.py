import os
from glob import glob

from setuptools import find_packages, setup

package_name = "deepsync_ros"

# Everything this package installs lives inside it (a workspace may hold the package folder
# alone). colcon runs setup.py with the package directory as the working directory for a plain
# build, but from its build directory (build/deepsync_ros, holding symlinks to the package's
# files) for --symlink-install, and it wants data_files sources as relative paths: so every
# source is written relative to the working directory, starting from where this file really is.
HERE = os.path.dirname(os.path.realpath(__file__))
SHARE = os.path.join("share", package_name)


def from_here(*parts: str) -> str:
    """A path inside this package, relative to the working directory."""
    return os.path.relpath(os.path.join(HERE, *parts))


def shared(folder: str, pattern: str = "*") -> tuple[str, list[str]]:
    """The files of one of this package's folders, installed under share/deepsync_ros/<folder>."""
    files = sorted(path for path in glob(from_here(folder, pattern)) if os.path.isfile(path))
    return os.path.join(SHARE, folder), files


setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(where=HERE, exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [from_here("resource", package_name)]),
        (SHARE, [from_here("package.xml")]),
        shared("launch", "*.launch.py"),
        shared("config"),
        shared(os.path.join("config", "towers")),
        shared(os.path.join("bags", "campus")),
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
