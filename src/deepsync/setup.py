from setuptools import find_packages, setup

package_name = "deepsync"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    # the shipped network (a few hundred kB); the demo's tower database and scenario (deepsync.eval.demo);
    # the message definitions bags are written with (bag/msg: deepsync_msgs'), read through
    # importlib.resources so that an installed package needs no checkout
    package_data={"deepsync.timing": ["timing_net.pt"], "deepsync": ["data/towers/*.yaml", "data/scenarios/*.yaml"],
                  "deepsync.bag": ["msg/*.msg"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "PyYAML>=6.0",
        "ruamel.yaml>=0.18",  # rewriting a tower database with its comments kept (deepsync calibrate)
        "rosbags>=0.11,<0.12",
        "mcap>=1.1",
        "pyproj>=3.6",
        "tqdm>=4.60",
        "threadpoolctl>=3.1",
        "matplotlib>=3.7",
        "sigmf>=1.14",
    ],
    # the timing network; the classical estimators, the nodes and the rest of the chain need none;
    # route sets, timing examples and route evaluations on a Ray cluster (deepsync.jobs); serial
    # ports at any baud rate (deepsync.sources.connections; termios otherwise); ray-traced
    # channels (deepsync.twin.raytrace: Sionna RT, footprints extruded with shapely, trimesh and
    # its triangulator; Dr.Jit also needs an LLVM >= 16, Debian's libllvm19). SoapySDR's
    # bindings are not on PyPI: they come with the library (docs/live_receivers.md)
    extras_require={"network": ["torch>=2.4"], "onnx": ["onnx>=1.16", "onnxscript>=0.5", "onnxruntime>=1.18"],
                    "ray": ["ray>=2.9"], "serial": ["pyserial>=3.5"],
                    "raytrace": ["sionna-rt>=2.2,<2.3", "shapely>=2.0", "trimesh>=4.0", "mapbox-earcut>=1.0"]},
    zip_safe=True,
    maintainer="DeepSync",
    maintainer_email="dev@deepsync.invalid",
    description="ROS-agnostic core of DeepSync: LTE envelope-detector localization.",
    license="Apache-2.0",
    entry_points={"console_scripts": ["deepsync = deepsync.cli:main"]},
)
