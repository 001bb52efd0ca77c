from setuptools import find_packages, setup

package_name = "formation_msgs_py"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={package_name: ["fastdds_profile.xml", "fastdds_loopback.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools", "formation_core"],
    extras_require={"test": ["pytest"]},  # colcon test runs pytest when "test" lists it
    zip_safe=True,
    maintainer="formation developers",
    maintainer_email="formation@example.com",
    description="The messages of formation: topics, CDR codec, message checks, QoS profiles, conversions.",
    license="Apache-2.0",
)
