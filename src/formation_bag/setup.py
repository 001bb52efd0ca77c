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
        "formation_core",
        "formation_msgs_py",
        "formation_ros",
        "formation_deploy",
        "numpy",
        "PyYAML",
        "rosbags",
        "mcap",
        "mcap-ros2-support",
    ],
    # colcon test runs pytest when "test" lists it; "live": the live view (--foxglove), whose foxglove-sdk has
    # no rosdep key
    extras_require={"test": ["pytest"], "live": ["foxglove-sdk"]},
    zip_safe=True,
    maintainer="formation developers",
    maintainer_email="formation@example.com",
    description="Formation runs as standard ROS 2 bags: writer, reader, repair, record and replay nodes, live view.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "formation-record = formation_bag.entry_points:record",
            "formation-replay = formation_bag.entry_points:replay",
            "formation-bag = formation_bag.cli:main",
        ],
    },
)
