"""ament_python package; also installs with plain pip (``pip install .``)."""

from glob import glob

from setuptools import find_packages, setup

package_name = "imu_array_ros"

# What some commands need beyond the core (imu_array_ros/util/extras.py: a command whose extra is missing
# says which to install): plots for --plot and report figures, bayes for `imu-array calibrate bayes`,
# noise for `imu-array calibrate noise`.
PLOTS = ["matplotlib>=3.7"]
BAYES = ["arviz>=0.20,<1", "h5netcdf>=1.0", "dask[distributed]>=2024.1"]
NOISE = ["allantools>=2019.9"]
EXTRAS = {
    "plots": PLOTS,
    "bayes": BAYES,
    "noise": NOISE,
    "all": PLOTS + BAYES + NOISE,
    "test": ["pytest>=7.4", "pytest-xdist>=3.5", "hypothesis>=6.0"] + PLOTS + BAYES + NOISE,  # the suite also tests the plots, the sampler, the noise
}

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks", "benchmarks.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    python_requires=">=3.10",
    # the core: fusion, calibration (but the Bayesian one), discovery, recordings, the nodes
    install_requires=[
        "setuptools",
        "numpy>=1.24",
        "scipy>=1.10",
        "pyyaml>=6.0",
        "mcap>=1.1",
        "rosbags>=0.10",
        "lz4>=4.0",
        "zstandard>=0.21",
        "pyserial>=3.5",
        "threadpoolctl>=3.1",
    ],
    zip_safe=True,
    maintainer="imu_array_ros maintainers",
    maintainer_email="imu-array-ros@example.com",
    description="Inertial sensor arrays as one high-grade IMU (ROS 2 Jazzy).",
    license="Apache-2.0",
    extras_require=EXTRAS,
    entry_points={
        "console_scripts": [
            "imu-array = imu_array_ros.cli:main",
            "driver_node = imu_array_ros.nodes.entry:driver_node",
            "fusion_node = imu_array_ros.nodes.entry:fusion_node",
            "calibration_node = imu_array_ros.nodes.entry:calibration_node",
        ],
    },
)
