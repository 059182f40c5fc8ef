"""The ROS 2 path: `colcon build` of this repository in a fresh workspace, and what it installs.

The workspace's src/ holds a copy of the tracked files (`git ls-files`), so what is built is what a
clone of the repository holds; colcon runs with this interpreter (the venv's, which has colcon and
the ament packages from requirements.lock).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPOSITORY = Path(__file__).resolve().parents[1]
PACKAGE = "touchdown_ros"
EXECUTABLES = ("touchdown", "touchdown_estimator")
BUILD_TIMEOUT_S = 300


def _tracked_files() -> list[str]:
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=REPOSITORY, capture_output=True, check=True)
    return [name for name in listed.stdout.decode().split("\0") if name and (REPOSITORY / name).is_file()]


def _clean_environment(workspace: Path) -> dict[str, str]:
    """This process's environment without its PYTHONPATH (the checkout), colcon's state kept in `workspace`."""
    environment = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "AMENT_PREFIX_PATH")}
    environment["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), environment.get("PATH", "")])
    environment["COLCON_HOME"] = str(workspace / "colcon_home")
    return environment


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    """A colcon workspace with this repository in src/, built with `colcon build --packages-select`."""
    root = tmp_path_factory.mktemp("colcon_ws")
    source = root / "src" / PACKAGE
    for name in _tracked_files():
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPOSITORY / name, source / name)
    build = subprocess.run(
        [sys.executable, "-m", "colcon", "build", "--packages-select", PACKAGE, "--base-paths", "src"],
        cwd=root, env=_clean_environment(root), capture_output=True, text=True, timeout=BUILD_TIMEOUT_S,
    )
    assert build.returncode == 0, f"colcon build failed:\n{build.stdout}\n{build.stderr}"
    assert f"Finished <<< {PACKAGE}" in build.stdout, build.stdout
    return root


def _site_packages(prefix: Path) -> Path:
    [site] = prefix.glob("lib/python3*/site-packages")
    return site


def test_colcon_build_installs_what_a_ros_user_needs(workspace):
    prefix = workspace / "install" / PACKAGE
    for name in EXECUTABLES:
        executable = prefix / "lib" / PACKAGE / name
        assert executable.is_file() and os.access(executable, os.X_OK), executable
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE).is_file()
    assert (prefix / "share" / PACKAGE / "package.xml").read_text() == (REPOSITORY / "package.xml").read_text()
    configs = sorted(path.name for path in (REPOSITORY / "config").iterdir() if path.suffix in (".yaml", ".xml"))
    assert configs and sorted(path.name for path in (prefix / "share" / PACKAGE / "config").iterdir()) == configs
    assert (_site_packages(prefix) / PACKAGE / "ros" / "node.py").is_file()
    assert (workspace / "install" / "setup.bash").is_file()


@pytest.mark.parametrize("name", EXECUTABLES)
def test_installed_executables_run_from_the_install_space(workspace, tmp_path, name):
    """Each executable where `ros2 run touchdown_ros <name>` finds it, with only the install space on the path."""
    prefix = workspace / "install" / PACKAGE
    environment = _clean_environment(workspace) | {"PYTHONPATH": str(_site_packages(prefix))}
    result = subprocess.run([str(prefix / "lib" / PACKAGE / name), "--help"], cwd=tmp_path, env=environment,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"usage: {name}"), result.stdout


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash to source install/setup.bash")
def test_sourced_workspace_imports_the_installed_package(workspace, tmp_path):
    """`source install/setup.bash`, as a ROS user does: the package imports from the install space and
    the ament index finds its share directory (where the node's configuration files are)."""
    script = (
        f"source {workspace / 'install' / 'setup.bash'} && exec {sys.executable} -c "
        "'import touchdown_ros.ros.node, touchdown_ros.cli; "
        "from ament_index_python.packages import get_package_share_directory as share; "
        f"print(touchdown_ros.__file__); print(share(\"{PACKAGE}\"))'"
    )
    result = subprocess.run(["bash", "-c", script], cwd=tmp_path, env=_clean_environment(workspace),
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    module_file, share = result.stdout.split()
    prefix = (workspace / "install" / PACKAGE).resolve()
    assert Path(module_file).resolve().is_relative_to(_site_packages(prefix))
    assert Path(share).resolve() == prefix / "share" / PACKAGE
