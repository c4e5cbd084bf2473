# Used by catkin_python_setup(); do not run by hand.
from setuptools import find_packages, setup
from catkin_pkg.python_setup import generate_distutils_setup

setup(**generate_distutils_setup(
    packages=find_packages("src"),
    package_dir={"": "src"},
    scripts=["nodes/mdr"],
))
