"""ament_python / pip build of touchdown_ros."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "touchdown_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "bench"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "jax>=0.4.30",
        "filelock",
        "numpy",
        "scipy",
        "matplotlib",
        "PyYAML",
        "rosbags>=0.10",
        "mcap",
    ],
    zip_safe=True,
    maintainer="touchdown_ros developers",
    maintainer_email="dev@touchdown-ros.invalid",
    description="PKBKR + EKF touchdown estimator for AMB auxiliary bearings",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "touchdown = touchdown_ros.cli:main",
            "touchdown_estimator = touchdown_ros.ros.node:main",
        ],
    },
)
