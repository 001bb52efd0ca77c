from setuptools import find_packages, setup

package_name = "formation_bag"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=[
        "setuptools",
        "formation_msgs_py",
        "formation_agent",
        "formation_sim",
        "numpy",
        "PyYAML",
        "rosbags",
        "mcap",
        "mcap-ros2-support",
    ],
    extras_require={"test": ["pytest"]},  # colcon test runs pytest when "test" lists it
    zip_safe=True,
    maintainer="formation developers",
    maintainer_email="formation@example.com",
    description="Record, replay and analyse formation runs as standard ROS 2 bags.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "formation-record = formation_bag.entry_points:record",
            "formation-replay = formation_bag.entry_points:replay",
            "formation-analyze = formation_bag.entry_points:analyze",
            "formation-rerun = formation_bag.entry_points:rerun",
            "formation-bag = formation_bag.cli:main",
        ],
    },
)
