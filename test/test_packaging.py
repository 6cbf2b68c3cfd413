"""Packaging checks: the ROS install layout, package.xml vs. the code, setup.py hygiene.

The colcon test builds this repository exactly as a ROS workspace would (``colcon build``,
plain, not ``--symlink-install``) into a temporary directory, so the source tree stays clean.
"""

from __future__ import annotations

import ast
import contextlib
import json
import os
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PKG = "mkf_ros"

# ROS packages the code may import; each one imported must be a dependency in package.xml.
ROS_PACKAGES = frozenset(
    {
        "rclpy",
        "sensor_msgs",
        "geometry_msgs",
        "std_msgs",
        "std_srvs",
        "diagnostic_msgs",
        "rcl_interfaces",
        "rosgraph_msgs",
        "builtin_interfaces",
        "ament_index_python",
        "tf2_ros",
    }
)
# Imported only behind ``try: ... except ImportError`` (no pip wheel exists): may be missing
# here, but declared in package.xml all the same (a real install has it).
OPTIONAL_ROS_PACKAGES = frozenset({"tf2_ros"})
# Any other imported module named like a ROS interface package counts as well (nav_msgs, ...).
ROS_INTERFACE_SUFFIXES = ("_msgs", "_srvs", "_interfaces")

CONSOLE_SCRIPTS = ("mkf", "estimator", "estimator_lifecycle", "player")


# ---------------------------------------------------------------- helpers


def _source_module_exists(dotted: str) -> bool:
    """True if the repo holds the module's source (what colcon installs)."""
    base = REPO.joinpath(*dotted.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def _is_ros_package(module: str) -> bool:
    """A known ROS package, or any interface package by the ROS naming convention."""
    return module in ROS_PACKAGES or module.endswith(ROS_INTERFACE_SUFFIXES)


def _setup_kwargs() -> dict[str, object]:
    """Keyword arguments of the ``setup(...)`` call in setup.py (without running it): literals,
    and names bound to a literal at module level (``name=package_name``); ``None`` for what
    is computed (e.g. data_files with glob)."""
    tree = ast.parse((REPO / "setup.py").read_text(), filename="setup.py")
    names: dict[str, object] = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 \
                and isinstance(node.targets[0], ast.Name):
            with contextlib.suppress(ValueError):
                names[node.targets[0].id] = ast.literal_eval(node.value)
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "setup":
            kwargs: dict[str, object] = {}
            for kw in node.keywords:
                if isinstance(kw.value, ast.Name) and kw.value.id in names:
                    kwargs[kw.arg] = names[kw.value.id]
                    continue
                try:
                    kwargs[kw.arg] = ast.literal_eval(kw.value)
                except ValueError:
                    kwargs[kw.arg] = None
            return kwargs
    raise AssertionError("setup.py has no setup(...) call")


def _package_xml() -> ET.Element:
    return ET.parse(REPO / "package.xml").getroot()


def _dependencies(root: ET.Element, *tags: str) -> set[str]:
    return {(el.text or "").strip() for tag in tags for el in root.findall(tag)}


def _imported_top_level_modules() -> dict[str, set[str]]:
    """Top-level module name -> files (relative) of mkf_ros/ that import it."""
    found: dict[str, set[str]] = {}
    for path in sorted((REPO / PKG).rglob("*.py")):
        rel = str(path.relative_to(REPO))
        try:
            tree = ast.parse(path.read_text(encoding="utf-8"), filename=rel)
        except SyntaxError as exc:
            pytest.fail(f"{rel}: cannot parse: {exc}")
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split(".")[0], set()).add(rel)
    return found


def _colcon() -> str:
    """The colcon of the running environment (installed by requirements/dev.txt)."""
    beside = Path(sys.executable).parent / "colcon"
    if beside.is_file() and os.access(beside, os.X_OK):
        return str(beside)
    found = shutil.which("colcon")
    if found:
        return found
    msg = f"colcon not installed next to {sys.executable} (pip install -r requirements/dev.txt)"
    if os.environ.get("CI"):
        pytest.fail(msg)
    pytest.skip(msg)


# ---------------------------------------------------------------- (a) colcon build


@pytest.fixture(scope="module")
def colcon_install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``colcon build`` of the repo in a temp workspace; returns ``<ws>/install/mkf_ros``."""
    colcon = _colcon()
    ws = tmp_path_factory.mktemp("colcon_ws")
    env = dict(os.environ)  # keep the ROS wheels' bootstrap variables intact
    env["COLCON_HOME"] = str(ws / "colcon_home")  # ignore a user's ~/.colcon defaults
    cmd = [
        colcon,
        "--log-base",
        str(ws / "log"),
        "build",
        "--base-paths",
        str(REPO),
        "--build-base",
        str(ws / "build"),
        "--install-base",
        str(ws / "install"),
        "--event-handlers",
        "console_direct+",
    ]
    proc = subprocess.run(
        cmd,
        cwd=ws,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    assert proc.returncode == 0, (
        f"colcon build failed (rc {proc.returncode}):\n{proc.stdout[-6000:]}\n{proc.stderr[-6000:]}"
    )
    prefix = ws / "install" / PKG
    assert prefix.is_dir(), f"no {prefix} after colcon build:\n{proc.stdout[-3000:]}"
    return prefix


def _site_packages(prefix: Path) -> Path:
    hits = sorted(prefix.glob("lib/python3*/site-packages")) + sorted(
        prefix.glob("local/lib/python3*/dist-packages")
    )
    assert hits, f"no site-packages under {prefix}"
    return hits[0]


def test_colcon_build_produces_ros_layout(colcon_install: Path) -> None:
    prefix = colcon_install
    marker = prefix / "share/ament_index/resource_index/packages" / PKG
    assert marker.is_file(), "ament index marker missing (ros2 run / get_package_share_directory)"
    assert (prefix / "share" / PKG / "package.xml").is_file()
    for name in CONSOLE_SCRIPTS:
        exe = prefix / "lib" / PKG / name
        assert exe.is_file(), f"{exe} missing (setup.cfg install_scripts / console_scripts)"
        assert os.access(exe, os.X_OK), f"{exe} not executable"
    # config/*.yaml and launch/*.launch.py are installed to share/mkf_ros/...
    for sub, pattern in (("config", "*.yaml"), ("launch", "*.launch.py")):
        want = {p.name for p in (REPO / sub).glob(pattern)}
        have = {p.name for p in (prefix / "share" / PKG / sub).glob(pattern)}
        assert want == have, f"share/{PKG}/{sub}: expected {sorted(want)}, installed {sorted(have)}"
    site = _site_packages(prefix)
    if (REPO / PKG / "__init__.py").is_file():
        assert (site / PKG / "__init__.py").is_file()
    assert (site / PKG / "py.typed").is_file(), "py.typed (PEP 561 marker) not installed"
    for excluded in ("test", "bench"):
        assert not (site / excluded).exists(), f"{excluded}/ must not be installed as a package"


def _installed_env(prefix: Path) -> dict[str, str]:
    """The environment ``. install/setup.sh`` would set for the colcon install ``prefix``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        filter(None, [str(_site_packages(prefix)), env.get("PYTHONPATH")]))
    env["AMENT_PREFIX_PATH"] = os.pathsep.join(
        filter(None, [str(prefix), env.get("AMENT_PREFIX_PATH")]))
    return env


def _run_installed(cmd: list[str], prefix: Path, timeout: float = 120
                   ) -> subprocess.CompletedProcess[str]:
    """``cmd`` run in the colcon install's environment, from ``prefix`` (not the repo: ``-c``
    puts the cwd first on sys.path)."""
    return subprocess.run(cmd, cwd=prefix, env=_installed_env(prefix), capture_output=True,
                          text=True, timeout=timeout, check=False)


def _assert_imported_from_install(module: str, prefix: Path) -> None:
    """``module`` is imported from the colcon install's site-packages, not from the repo."""
    site = _site_packages(prefix)
    where = _run_installed([sys.executable, "-c", f"import {module} as m; print(m.__file__)"],
                           prefix)
    assert where.returncode == 0, where.stderr
    assert Path(where.stdout.strip()).resolve().is_relative_to(site.resolve()), (
        f"{module} imported from {where.stdout.strip()}, not from the colcon install {site}"
    )


def test_installed_mkf_runs_help(colcon_install: Path) -> None:
    if not _source_module_exists(f"{PKG}.cli.main"):
        pytest.skip(f"{PKG}/cli/main.py does not exist yet")
    prefix = colcon_install
    _assert_imported_from_install(PKG, prefix)
    proc = _run_installed([str(prefix / "lib" / PKG / "mkf"), "--help"], prefix)
    assert proc.returncode == 0, f"mkf --help: rc {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert proc.stdout.strip(), "mkf --help printed nothing"


@pytest.mark.slow
@pytest.mark.ros
def test_installed_estimator_runs(colcon_install: Path) -> None:
    """``ros2 run mkf_ros estimator``: the colcon-installed executable starts, is driven by a
    separate client process (topics, SetParameters, ~/reset) and stops cleanly on SIGINT:
    the same session and checks as the editable install's (test/ros/test_process.py).

    The compiled kernels come from the per-user numba cache shared with the source tree
    (mkf_ros/core/_jit.py keys it on the kernel sources), so this is seconds, not the ~1 min
    of a cold compile, unless the kernels changed since the last run.
    """
    from proc_session import SESSION_ROS_ARGS, check_session, run_node_and_client

    prefix = colcon_install
    exe = prefix / "lib" / PKG / "estimator"
    help_ = _run_installed([str(exe), "--help"], prefix)
    assert help_.returncode == 0 and "imu/data_raw" in help_.stdout, help_.stderr
    res, err, rc = run_node_and_client(
        [str(exe), "--ros-args", "-r", "__node:=colcon_estimator", *SESSION_ROS_ARGS],
        _installed_env(prefix), "/colcon_estimator", cwd=prefix,
        client_args=("--timeout", "200"))
    check_session(res, err, rc)
    _assert_imported_from_install("mkf_ros.ros.estimator_node", prefix)


# ---------------------------------------------------------------- (b) package.xml


def test_package_xml_metadata_matches_setup_py() -> None:
    root = _package_xml()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == PKG
    assert root.findtext("export/build_type") == "ament_python"
    kwargs = _setup_kwargs()
    assert kwargs["name"] == PKG, "name differs: package.xml vs setup.py"
    assert root.findtext("license") == kwargs.get("license", "Apache-2.0") == "Apache-2.0"


def _defined_version() -> str:
    """``__version__`` of mkf_ros/_version.py, the one definition (read as source)."""
    tree = ast.parse((REPO / PKG / "_version.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "__version__":
            value = ast.literal_eval(node.value)
            assert isinstance(value, str)
            return value
    raise AssertionError("mkf_ros/_version.py defines no __version__")


def test_version_is_defined_once_and_package_xml_agrees() -> None:
    """setup.py and ``mkf_ros.__version__`` read the version from mkf_ros/_version.py; no other
    Python file spells it; package.xml (a literal, for ROS tools) carries the same number."""
    import mkf_ros

    version = _defined_version()
    assert _package_xml().findtext("version") == version, (
        f"package.xml <version> differs from mkf_ros/_version.py ({version})")
    assert mkf_ros.__version__ == version
    setup_py = (REPO / "setup.py").read_text()
    assert "version=read_version()" in setup_py, "setup.py must read the version, not spell it"
    spelled = [str(p.relative_to(REPO)) for p in [REPO / "setup.py", *(REPO / PKG).rglob("*.py")]
               if p.name != "_version.py" and f'"{version}"' in p.read_text()]
    assert not spelled, f"the version spelled outside mkf_ros/_version.py: {spelled}"


def test_package_xml_is_valid_for_catkin_pkg() -> None:
    catkin_pkg_package = pytest.importorskip("catkin_pkg.package")  # comes with colcon-ros
    pkg = catkin_pkg_package.parse_package(str(REPO / "package.xml"))
    pkg.validate()
    assert pkg.get_build_type() == "ament_python"


def test_package_xml_lists_every_imported_ros_package() -> None:
    deps = _dependencies(_package_xml(), "depend", "exec_depend")
    imported = _imported_top_level_modules()
    missing = {
        mod: sorted(files)
        for mod, files in imported.items()
        if _is_ros_package(mod) and mod not in OPTIONAL_ROS_PACKAGES and mod not in deps
    }
    assert not missing, f"imported ROS packages missing from package.xml <exec_depend>: {missing}"


#: rosdistro's rosdep/python.yaml, transcribed for Ubuntu: the key that installs each Python
#: distribution (PyPI name, normalised) and what it installs there.
ROSDEP_PYTHON_KEYS = {
    "setuptools": ("python3-setuptools", "apt: python3-setuptools"),
    "numpy": ("python3-numpy", "apt: python3-numpy"),
    "numba": ("python3-numba", "apt: python3-numba"),
    "rosbags": ("python3-rosbags-pip", "pip: rosbags"),  # rosdistro PR #37795
    "matplotlib": ("python3-matplotlib", "apt: python3-matplotlib"),
    "tqdm": ("python3-tqdm", "apt: python3-tqdm"),
    "pyyaml": ("python3-yaml", "apt: python3-yaml"),
}


def _requirement_name(req: str) -> str:
    m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", req)
    assert m, f"not a requirement: {req!r}"
    return re.sub(r"[-_.]+", "-", m.group(1)).lower()


def test_every_install_requires_entry_has_its_rosdep_key() -> None:
    """``rosdep install --from-paths src`` installs what the package needs: each
    install_requires entry of setup.py is declared in package.xml through the rosdep key that
    installs it (rosbags through python3-rosbags-pip), and no Python key is left over."""
    reqs = _setup_kwargs().get("install_requires")
    assert isinstance(reqs, list) and reqs
    deps = _dependencies(_package_xml(), "depend", "exec_depend")
    needed = set()
    for req in reqs:
        name = _requirement_name(req)
        assert name in ROSDEP_PYTHON_KEYS, (
            f"install_requires has {req!r}: find its rosdep key (rosdistro rosdep/python.yaml), "
            "add it to package.xml and to ROSDEP_PYTHON_KEYS here")
        key = ROSDEP_PYTHON_KEYS[name][0]
        assert key in deps, f"package.xml lacks <exec_depend>{key}</exec_depend> ({req})"
        needed.add(key)
    python_keys = {d for d in deps if d.startswith("python3-")}
    assert python_keys == needed, f"package.xml declares more: {sorted(python_keys - needed)}"


def test_package_xml_declares_tf2_ros() -> None:
    """publish_tf works after ``rosdep install``: tf2_ros is an exec dependency."""
    assert "tf2_ros" in _dependencies(_package_xml(), "depend", "exec_depend")


# ---------------------------------------------------------------- (c) setup.py


def test_install_requires_has_no_ros_wheels() -> None:
    reqs = _setup_kwargs().get("install_requires")
    assert isinstance(reqs, list) and reqs, "install_requires must be a literal list"
    ros_wheels = [r for r in reqs if r.lower().replace("_", "-").startswith("ros-")]
    assert not ros_wheels, (
        f"ros-* wheels belong in requirements/ros-jazzy.txt (dev/CI), not install_requires: "
        f"{ros_wheels}"
    )
    assert "tests_require" not in _setup_kwargs(), "drop tests_require (setuptools warns, colcon)"


def _pins(path: Path) -> dict[str, str]:
    """``name == version`` pins of a requirements file and the files it includes (-r)."""
    pins: dict[str, str] = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line.startswith("-r "):
            pins.update(_pins(path.parent / line[3:].strip()))
        elif "==" in line:
            name, version = line.split("==", 1)
            pins[name.split("[", 1)[0].strip().lower().replace("_", "-")] = version.strip()
    return pins


@pytest.mark.parametrize("pinned", ["dev.txt", "ubuntu-noble.txt"])
def test_every_supported_set_satisfies_install_requires(pinned: str) -> None:
    """Both sets CI builds (the current releases; Ubuntu 24.04's, what rosdep installs for
    Jazzy) are inside setup.py's declared ranges, and pin every runtime requirement."""
    from packaging.requirements import Requirement

    pins = _pins(REPO / "requirements" / pinned)
    reqs = [Requirement(r) for r in _setup_kwargs()["install_requires"]]  # type: ignore[union-attr]
    missing = [r.name for r in reqs if r.name.lower() not in pins]
    outside = [f"{r.name}=={pins[r.name.lower()]} (needs {r.specifier})" for r in reqs
               if r.name.lower() in pins and pins[r.name.lower()] not in r.specifier]
    assert not missing and not outside, (missing, outside)
    if pinned == "ubuntu-noble.txt":  # Ubuntu 24.04's own versions
        assert (pins["numba"], pins["numpy"]) == ("0.58.1", "1.26.4")


# ---------------------------------------------------------------- environment


_ROS_VARS = ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID", "ROS_LOG_DIR")


def _env_from(setup: list[str], domain: str | None) -> dict[str, str]:
    """The ROS variables a child sees after ``setup`` ran in an environment without them (or
    with only ``ROS_DOMAIN_ID=domain``), printed by the child itself."""
    env = {k: v for k, v in os.environ.items() if k not in _ROS_VARS}
    if domain is not None:
        env["ROS_DOMAIN_ID"] = domain
    out = subprocess.run(setup, env=env, capture_output=True, text=True, timeout=60,
                         check=True, cwd=REPO).stdout
    return dict(line.split("=", 1) for line in out.splitlines() if line.startswith("ROS_"))


@pytest.mark.parametrize("entry", ["run", "conftest"])
@pytest.mark.parametrize("domain", [None, "77"])
def test_ros_discovery_is_local(entry: str, domain: str | None) -> None:
    """``./run`` (its ``ros_env``) and test/conftest.py, started from an environment without
    the ROS variables, give every child LOCALHOST discovery, a domain in 1..101 (a preset one
    kept) and a log directory that exists."""
    show = "; ".join(f'echo {k}="${k}"' for k in _ROS_VARS)
    if entry == "run":  # the function of ./run, sourced without running ./run's commands
        setup = ["bash", "-c", f'eval "$(sed -n \'/^ros_env()/,/^}}/p\' run)"; ros_env; {show}']
    else:
        code = ("import os, runpy; runpy.run_path('test/conftest.py'); "
                f"print('\\n'.join(k + '=' + os.environ[k] for k in {_ROS_VARS!r}))")
        setup = [sys.executable, "-c", code]
    got = _env_from(setup, domain)
    assert got["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert 1 <= int(got["ROS_DOMAIN_ID"]) <= 101
    if domain is not None:
        assert got["ROS_DOMAIN_ID"] == domain
    assert Path(got["ROS_LOG_DIR"]).is_dir()


@pytest.mark.ros
def test_rclpy_pub_sub_in_one_process(ros_context) -> None:
    """The pinned ROS wheels work: two nodes exchange a std_msgs/String."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_msgs.msg import String

    assert ros_context.get_domain_id() == int(os.environ["ROS_DOMAIN_ID"])
    talker = Node("packaging_talker", context=ros_context)
    listener = Node("packaging_listener", context=ros_context)
    got: list[str] = []
    listener.create_subscription(String, "packaging_chatter", lambda m: got.append(m.data), 10)
    pub = talker.create_publisher(String, "packaging_chatter", 10)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(talker)
    executor.add_node(listener)
    try:
        for _ in range(200):  # <= ~20 s, normally a few iterations
            if got:
                break
            if pub.get_subscription_count() > 0:
                pub.publish(String(data="hello"))
            executor.spin_once(timeout_sec=0.1)
        assert got and got[0] == "hello"
    finally:
        executor.shutdown()
        talker.destroy_node()
        listener.destroy_node()


# ---------------------------------------------------------------- (c) pip, build isolation

_LOAD_CHECK = """
import json, numba.core.event as ev
passes = [0]
class Count(ev.Listener):  # a compiler pass runs only when something compiles, not on a load
    def on_start(self, event):
        passes[0] += 1
    def on_end(self, event):
        pass
ev.register("numba:run_pass", Count())
import mkf_ros
from mkf_ros.core import _jit
mkf_ros.kernels.warmup_installed()  # the simulator's kernel (mkf synth) is shipped too
print(json.dumps({"file": mkf_ros.__file__, "passes": passes[0],
                  "packaged": (_jit.PACKAGED_CACHE_ROOT / f"numba-{_jit.KERNEL_HASH}").is_dir()}))
"""


def test_pip_install_with_build_isolation_ships_the_compiled_kernels(tmp_path: Path) -> None:
    """``pip install .`` with pip's default build isolation, the most common install path: the
    isolated build environment gets numba from pyproject.toml's build requirements, so
    ``build_py`` compiles the kernels into the package, and the first start of the installed
    package loads them from there into an empty user cache (no compiler pass runs). The build
    environment is held to the running numba and NumPy (``PIP_CONSTRAINT``, which pip passes
    on to it): kernels compiled by another numba version are not loaded."""
    import numba
    import numpy

    src = tmp_path / "src"  # pip builds a local project in place: keep the checkout clean
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(
        ".git", ".venv", "build", "install", "log", "*.egg-info", "__pycache__",
        ".pytest_cache", ".ruff_cache", ".mypy_cache", ".hypothesis"))
    constraints = tmp_path / "constraints.txt"
    constraints.write_text(f"numba=={numba.__version__}\nnumpy=={numpy.__version__}\n")
    target = tmp_path / "site"
    env = dict(os.environ, PIP_CONSTRAINT=str(constraints))
    env.pop("MKF_ROS_NO_PRECOMPILE", None)
    proc = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--target",
                           str(target), str(src)], env=env, capture_output=True, text=True,
                          timeout=900, check=False)
    assert proc.returncode == 0, (
        f"pip install failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    assert "numba not importable" not in proc.stderr, proc.stderr[-2000:]
    run_env = dict(os.environ, PYTHONPATH=str(target),
                   MKF_ROS_CACHE_DIR=str(tmp_path / "user-cache"))
    out = subprocess.run([sys.executable, "-c", _LOAD_CHECK], env=run_env, cwd=tmp_path,
                         capture_output=True, text=True, timeout=300, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert Path(got["file"]).is_relative_to(target), got
    assert got["packaged"], f"no compiled kernels in the installed package: {got}"
    # PEP 561: the built wheel ships the typed-package marker
    assert (target / PKG / "py.typed").is_file(), "py.typed missing from the installed wheel"
    assert got["passes"] == 0, f"the first start compiled ({got['passes']} compiler passes)"
