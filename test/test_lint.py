"""The lint tests an ament_python package carries: ament_flake8 and ament_pep257, configured in setup.cfg."""
from __future__ import annotations

import configparser
from pathlib import Path

import pytest
from ament_flake8.main import main_with_errors as flake8_main
from ament_pep257.main import main as pep257_main

REPOSITORY = Path(__file__).resolve().parents[1]
SETUP_CFG = REPOSITORY / "setup.cfg"
CHECKED = [str(REPOSITORY / name) for name in ("touchdown_ros", "test", "bench", "scripts", "setup.py")]


def flake8(paths: list[str]) -> tuple[int, list[str]]:
    return flake8_main(argv=["--config", str(SETUP_CFG), *paths])


def pep257(paths: list[str]) -> int:
    parser = configparser.ConfigParser()
    parser.read(SETUP_CFG)
    ignored = [code.strip() for code in parser["pydocstyle"]["ignore"].split(",")]
    return pep257_main(argv=["--ignore", *ignored, "--", *paths])


@pytest.mark.flake8
def test_flake8():
    code, errors = flake8(CHECKED)
    assert code == 0, f"ament_flake8 found {len(errors)} code style errors / warnings:\n" + "\n".join(errors)


@pytest.mark.pep257
def test_pep257():
    assert pep257(CHECKED) == 0, "ament_pep257 found docstring style errors (listed above)"


def test_the_linters_report_a_real_violation(tmp_path):
    """The configuration still lets each linter fail: an unused import, a docstring over its summary's line."""
    bad = tmp_path / "bad.py"
    bad.write_text('"""A module."""\nimport os\n\n\ndef f():\n    """  Padded summary."""\n')
    code, errors = flake8([str(bad)])
    assert code != 0 and any("F401" in error for error in errors), errors
    assert pep257([str(bad)]) != 0
