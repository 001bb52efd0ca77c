from setuptools import find_packages, setup

package_name = "formation_deploy"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools", "formation_core", "formation_msgs_py", "formation_ros", "cryptography", "PyYAML"],
    extras_require={"test": ["pytest"]},  # colcon test runs pytest when "test" lists it
    zip_safe=True,
    maintainer="formation developers",
    maintainer_email="formation@example.com",
    description="Deployment and security: compose generator, keys, TLS profiles, intruder detection.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "formation-compose = formation_deploy.compose:main",
            "formation-keys = formation_deploy.keys_cli:main",
        ],
    },
)
