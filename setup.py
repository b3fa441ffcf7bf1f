"""Package layout (metadata and dependencies are in pyproject.toml).

The shipped config files live in the repository's ``config/`` folder, where users and the README
find them; they are installed as the data-only package ``tmrl.config_files``.
"""

from setuptools import find_packages, setup

setup(
    packages=find_packages(include=["tmrl", "tmrl.*"]) + ["tmrl.config_files"],
    package_dir={"tmrl.config_files": "config"},
    package_data={"tmrl": ["resources/*.json"], "tmrl.config_files": ["*.json"]},
)
