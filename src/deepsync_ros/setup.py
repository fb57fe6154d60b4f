import os
from glob import glob

from setuptools import find_packages, setup

package_name = "deepsync_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        # glob() yields [] while launch/ is empty or absent, which setuptools accepts.
        (
            os.path.join("share", package_name, "launch"),
            glob(os.path.join("launch", "*.launch.py")),
        ),
    ],
    python_requires=">=3.10",
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="DeepSync",
    maintainer_email="dev@deepsync.invalid",
    description="ROS 2 binding of DeepSync: rclpy nodes, launch files, conversions and bag replay.",
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},
    entry_points={"console_scripts": []},
)
