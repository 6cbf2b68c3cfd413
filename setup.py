"""ament_python packaging of mkf_ros.

Runtime ROS dependencies live in package.xml (rosdep / apt on a ROS machine);
ros-* PyPI wheels are for development and CI only (requirements/ros-jazzy.txt)
and must never appear in install_requires.
"""

import os
import re
import shutil
import subprocess
import sys
from glob import glob

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

package_name = "mkf_ros"


def read_version() -> str:
    """The one definition of the version, ``mkf_ros/_version.py`` (read, not imported: the
    build may lack the runtime dependencies). package.xml repeats it as a literal for ROS;
    test/test_packaging.py checks that they agree."""
    here = os.path.dirname(os.path.abspath(__file__))
    with open(os.path.join(here, package_name, "_version.py"), encoding="utf-8") as f:
        found = re.search(r'^__version__ = "([^"]+)"$', f.read(), re.MULTILINE)
    if found is None:
        raise RuntimeError(f"no __version__ = \"...\" line in {package_name}/_version.py")
    return found.group(1)


class BuildPyWithKernels(build_py):
    """``build_py`` plus the install-time kernel compile (``mkf_ros.kernels.precompile``,
    about a minute on 2 cores): the numba kernels are compiled into the built package
    (``mkf_ros/_kernels/``) so that the first start of the installed node loads them instead
    of compiling. pip's isolated build environment gets numba and NumPy from pyproject.toml's
    build requirements. Skipped, with a note, when numba cannot be imported by the build or
    when ``MKF_ROS_NO_PRECOMPILE=1``; the kernels are then compiled on first use."""

    def run(self) -> None:
        super().run()
        if (self.dry_run or getattr(self, "editable_mode", False)
                or os.environ.get("MKF_ROS_NO_PRECOMPILE") == "1"):
            return  # (an editable checkout precompiles into its own tree: ./run setup)
        lib = os.path.abspath(self.build_lib)
        code = ("import mkf_ros.kernels as k, mkf_ros.core._jit as j; "
                "k.precompile(j.PACKAGED_CACHE_ROOT)")
        path = os.pathsep.join(filter(None, [lib, os.environ.get("PYTHONPATH")]))
        env = dict(os.environ, PYTHONPATH=path,
                   MKF_ROS_CACHE_DIR=os.path.join(lib, package_name, "_kernels"))
        try:
            import numba  # noqa: F401
        except ImportError:
            print("mkf_ros: numba not importable at build time; kernels will compile on first use",
                  file=sys.stderr)
            return
        here = os.path.join(os.path.dirname(os.path.abspath(__file__)), package_name, "_kernels")
        if os.path.isdir(here):  # a checkout that compiled them already (./run setup): reuse
            shutil.copytree(here, os.path.join(lib, package_name, "_kernels"), dirs_exist_ok=True)
        print("mkf_ros: compiling the filter kernels into the package (about a minute; once "
              "per kernel version) ...", file=sys.stderr)
        subprocess.run([sys.executable, "-c", code], env=env, cwd=lib, check=True)


setup(
    name=package_name,
    version=read_version(),
    description="Manifold Kalman Filter (MEKF/MUKF) attitude estimation for ROS 2",
    license="Apache-2.0",
    maintainer="mkf_ros maintainers",
    maintainer_email="maintainers@users.noreply.h-seed-5101cbd9.example",
    packages=find_packages(exclude=["test*", "bench*"]),
    # PEP 561: the package is typed (its annotations are checked by test/test_typecheck.py)
    package_data={package_name: ["py.typed"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=[
        "setuptools",
        # two supported sets, both tested in CI (.ci/run): Ubuntu 24.04's packages, which
        # rosdep installs for ROS 2 Jazzy (requirements/ubuntu-noble.txt: numba 0.58.1,
        # NumPy 1.26.4, ...), and the current releases (requirements/dev.txt: numba 0.68,
        # NumPy 2.4); docs/estimator.md § Start-up
        "numpy>=1.26.4",
        "numba>=0.58.1",
        "rosbags>=0.11,<0.12",  # mkf_ros.bags.writer extends its storage writers' internals
        "matplotlib>=3.6.3",
        "tqdm>=4.60",
        "pyyaml>=6.0.1",
    ],
    extras_require={
        # `mkf study/process --scheduler tcp://HOST:8786`: work units on a Dask cluster
        # (docs/study/cluster.md); never needed by the nodes
        "cluster": ["dask[distributed]>=2024.1"],
    },
    python_requires=">=3.10",
    cmdclass={"build_py": BuildPyWithKernels},
    zip_safe=True,
    entry_points={
        "console_scripts": [
            "mkf = mkf_ros.cli.main:main",
            "estimator = mkf_ros.ros.estimator_main:main",
            "estimator_lifecycle = mkf_ros.ros.lifecycle:lifecycle_main",
            "player = mkf_ros.ros.player_node:main",
        ],
    },
)
