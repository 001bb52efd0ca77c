from setuptools import find_packages, setup

package_name = "formation_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools", "PyYAML"],
    extras_require={"test": ["pytest"]},  # colcon test runs pytest when "test" lists it
    zip_safe=True,
    maintainer="formation developers",
    maintainer_email="formation@example.com",
    description="The nodes' rclpy plumbing: rclpy internals, parameters, shutdown, formation-param.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "formation-param = formation_ros.param_cli:main",
        ],
    },
)
