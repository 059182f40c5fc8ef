"""The lint tests an ament_python package carries: ament_flake8 and ament_pep257, configured in setup.cfg."""
from __future__ import annotations

import configparser
import subprocess
import sys
from pathlib import Path

import pytest

REPOSITORY = Path(__file__).resolve().parents[1]
SETUP_CFG = REPOSITORY / "setup.cfg"
CHECKED = [str(REPOSITORY / name) for name in ("touchdown_ros", "test", "bench", "scripts", "setup.py")]


def _ament(linter: str, argv: list[str]) -> subprocess.CompletedProcess:
    """Run ament_<linter> in its own process (flake8 forks its workers; this one has JAX's threads)."""
    main = f"import sys; from ament_{linter}.main import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", main, *argv], cwd=REPOSITORY, capture_output=True, text=True,
                          timeout=300)


def flake8(paths: list[str]) -> subprocess.CompletedProcess:
    return _ament("flake8", ["--config", str(SETUP_CFG), *paths])


def pep257(paths: list[str]) -> subprocess.CompletedProcess:
    parser = configparser.ConfigParser()
    parser.read(SETUP_CFG)
    ignored = [code.strip() for code in parser["pydocstyle"]["ignore"].split(",")]
    return _ament("pep257", ["--ignore", *ignored, "--", *paths])


@pytest.mark.flake8
def test_flake8():
    result = flake8(CHECKED)
    assert result.returncode == 0, f"ament_flake8 found code style errors:\n{result.stdout}{result.stderr}"


@pytest.mark.pep257
def test_pep257():
    result = pep257(CHECKED)
    assert result.returncode == 0, f"ament_pep257 found docstring style errors:\n{result.stdout}{result.stderr}"


def test_the_linters_report_a_real_violation(tmp_path):
    """The configuration still lets each linter fail: an unused import, a line over 120 characters, a
    docstring padded with spaces."""
    bad = tmp_path / "bad.py"
    long_line = "x = " + repr("a" * 120)
    bad.write_text(f'"""A module."""\nimport os\n\n{long_line}\n\n\ndef f():\n    """  Padded summary."""\n')
    result = flake8([str(bad)])
    assert result.returncode == 1 and "F401" in result.stdout and "E501" in result.stdout, result.stdout + result.stderr
    result = pep257([str(bad)])
    assert result.returncode == 1 and "D210" in result.stderr, result.stdout + result.stderr
