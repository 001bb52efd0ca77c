from setuptools import find_packages, setup

package_name = "formation_sim"

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
        "formation_agent",
        "formation_bag",
        "numpy",
        "matplotlib",
        "scipy",
        "PyYAML",
        "pillow",
    ],
    # colcon test runs pytest when "test" lists it; "dask": formation-campaign --scheduler
    extras_require={"test": ["pytest"], "dask": ["distributed"]},
    zip_safe=True,
    maintainer="formation developers",
    maintainer_email="formation@example.com",
    description="Plant, judge, headless runner, simulator node, launcher, reports, offline runs from a bag.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "formation-check = formation_sim.cli.check:main",
            "formation-headless = formation_sim.cli.headless:main",
            "formation-sim = formation_sim.cli.sim:sim",
            "formation-launch = formation_sim.launch.launcher:main",
            "formation-generate = formation_sim.cli.generate:main",
            "formation-campaign = formation_sim.cli.campaign:main",
            "formation-analyze = formation_sim.offline.entry_points:analyze",
            "formation-rerun = formation_sim.offline.entry_points:rerun",
        ],
    },
)
