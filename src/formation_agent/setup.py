from setuptools import find_packages, setup

package_name = "formation_agent"

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
    ],
    extras_require={"test": ["pytest"]},  # colcon test runs pytest when "test" lists it
    zip_safe=True,
    maintainer="formation developers",
    maintainer_email="formation@example.com",
    description="Prescribed-performance formation controller and the agent node.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "formation-agent = formation_agent.entry_point:main",
        ],
    },
)
