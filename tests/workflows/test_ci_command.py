"""CI runs exactly the README's test command, and that command lists the ten slowest tests."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def readme_test_command() -> str:
    text = (ROOT / "README.md").read_text()
    (line,) = [l for l in text.splitlines() if l.startswith('pip install -e ".[test]"')]
    return line


def ci_test_command() -> str:
    lines = [l for l in (ROOT / ".ci" / "run").read_text().splitlines()
             if "pytest" in l and not l.startswith("#")]
    (line,) = lines
    return line


def test_ci_runs_the_readme_test_command():
    readme = readme_test_command().split("&&")[1].strip()
    ci = ci_test_command().split("&&")[1].strip()
    assert ci == readme
    # the same install too, CI's only quieter
    assert re.sub(r"\s-q\s", " ", ci_test_command().split("&&")[0]) == \
        readme_test_command().split("&&")[0]


def test_the_test_command_prints_the_ten_slowest_tests():
    assert "--durations=10" in readme_test_command().split()
    assert "--durations=10" in ci_test_command().split()
