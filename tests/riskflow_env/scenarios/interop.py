"""Skip a test module, with the reason, when a library of the ``[interop]`` extra is absent.

commonroad-io's generated protobuf modules need protobuf 3.20, or its pure-Python parser
with a newer protobuf: the variable is set before anything here imports protobuf.
"""

from __future__ import annotations

import importlib
import os

import pytest

os.environ.setdefault("PROTOCOL_BUFFERS_PYTHON_IMPLEMENTATION", "python")


def import_error(*modules: str) -> str | None:
    """Why one of ``modules`` does not import, or None when they all do."""
    for module in modules:
        try:
            importlib.import_module(module)
        except Exception as err:  # protobuf's TypeError is not an ImportError
            return f"{module} does not import ({type(err).__name__}: {str(err)[:200]})"
    return None


def require(*modules: str) -> None:
    """Skip the calling module unless every module of ``modules`` imports."""
    error = import_error(*modules)
    if error is not None:
        pytest.skip(
            f"{error}: pip install -e '.[interop]' (docs/how-to/exchange.md)",
            allow_module_level=True,
        )


def asam_issues(path) -> list[tuple[str, str, str]]:
    """(checker, severity, description) of every issue ASAM's checker bundle for ``path``'s
    format (``.xosc``: asam-qc-openscenarioxml, ``.xodr``: asam-qc-opendrive) finds, plus
    every checker that did not complete or skip."""
    import logging

    from qc_baselib import Configuration, Result

    if str(path).endswith(".xodr"):
        from qc_opendrive import constants
        from qc_opendrive.main import run_checks
    else:
        from qc_openscenario import constants
        from qc_openscenario.main import run_checks
    config = Configuration()
    config.set_config_param("InputFile", str(path))
    result = Result()
    result.register_checker_bundle(
        name=constants.BUNDLE_NAME, description="", version=constants.BUNDLE_VERSION, summary=""
    )
    result.set_result_version(version=constants.BUNDLE_VERSION)
    logging.disable(logging.INFO)
    try:
        run_checks(config, result)
    finally:
        logging.disable(logging.NOTSET)
    found = []
    for checker in result.get_checker_results(constants.BUNDLE_NAME):
        if checker.status.name not in ("COMPLETED", "SKIPPED"):
            found.append((checker.checker_id, checker.status.name, checker.summary))
        for issue in checker.issues:
            text = "; ".join(location.description for location in issue.locations)
            found.append((checker.checker_id, issue.level.name, text))
    return found
