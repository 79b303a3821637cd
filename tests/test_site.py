"""The documentation site builds without a warning, and the changelog follows the version.

``mkdocs build --strict`` (mkdocs.yml) turns every warning into a failure: a broken link or
anchor between pages, a page of the nav that does not exist, a docstring reference
mkdocstrings cannot resolve, a console script without its generated reference
(docs/hooks/cli_reference.py). The site is built into a scratch folder, never into the
repository. Needs the docs extra (``pip install -e ".[docs]"``; ``.ci/run`` installs it);
in the ``docs`` tier, which the default run leaves out (``python -m pytest -m docs``).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import riskflow_env

pytestmark = pytest.mark.docs

ROOT = Path(__file__).resolve().parents[1]
NEEDS_EXTRA = 'the docs extra is not installed: pip install -e ".[docs]"'
TIMEOUT = 600  # [s] the build takes about 20 s on a shared 2-core machine


def _pyproject_version() -> str:
    match = re.search(r'^version = "([^"]+)"', (ROOT / "pyproject.toml").read_text(), re.M)
    assert match, "pyproject.toml has no [project] version line"
    return match.group(1)


def test_site_builds_strict(tmp_path):
    for module in ("mkdocs", "material", "mkdocstrings_handlers.python"):
        pytest.importorskip(module, reason=NEEDS_EXTRA)
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
               str(ROOT / "mkdocs.yml"), "--site-dir", str(tmp_path / "site")]  # fmt: skip
    result = subprocess.run(
        command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=TIMEOUT
    )
    output = result.stdout + result.stderr
    warnings = [line for line in output.splitlines() if line.startswith(("WARNING", "ERROR"))]
    assert result.returncode == 0 and not warnings, (
        f"mkdocs build --strict failed (exit {result.returncode}):\n"
        + "\n".join(warnings or output.splitlines()[-40:])
    )
    for page in ("index.html", "reference/cli/index.html", "reference/configs/index.html"):
        assert (tmp_path / "site" / page).is_file(), f"the site has no {page}"
    cli = (tmp_path / "site" / "reference/cli/index.html").read_text(encoding="utf-8")
    for option in ("--scenes", "--recipe", "--methods", "--planner"):
        assert option in cli, f"the generated command-line reference lacks {option}"


def test_version_follows_pyproject_and_the_changelog():
    version = _pyproject_version()
    assert riskflow_env.__version__ == version, (
        f"riskflow_env.__version__ is {riskflow_env.__version__}, pyproject.toml says "
        f"{version}: reinstall the package (pip install -e .)"
    )
    changelog = (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    assert f"## [{version}]" in changelog, f"CHANGELOG.md has no '## [{version}]' section"
    assert '--8<-- "CHANGELOG.md"' in (ROOT / "docs" / "changelog.md").read_text()
