"""The planner under test, named on a command line: a built-in, an import path or a file.

:func:`load_planner` turns a *planner spec* into an
:class:`~policies.planners.base.EgoPlanner`:

=================================  =========================================================
``idm`` (a name of ``PLANNERS``)   a built-in planner (:data:`policies.planners.PLANNERS`),
                                   with the env's dynamics bounds
``package.module:object``          ``object`` of an importable module
``path/to/file.py:object``         ``object`` of a Python file (its folder is put on
                                   ``sys.path``, as ``python file.py`` does, so that it can
                                   import its neighbours; a file is run once per process,
                                   as a module is imported once)
=================================  =========================================================

``object`` is a planner (a callable ``planner(observation, view) -> action``, a function or
an object with ``__call__``) or a class or factory called with no argument that returns
one: a class is always instantiated, a function that takes no required argument is called.
Each call of :func:`load_planner` gives a fresh planner (a fresh instance, for a class or a
factory), which is how each worker process gets its own.
"""

from __future__ import annotations

import difflib
import hashlib
import importlib
import importlib.util
import inspect
import sys
from pathlib import Path

from policies.cli_inputs import did_you_mean
from policies.planners import PLANNERS, EgoPlanner, make_planner
from riskflow_env.config import DynamicsConfig

FILE_MODULE_PREFIX = "riskflow_stress_planner_"  # modules of planner files
FORMS = "a built-in name ({names}), package.module:object or path/to/file.py:object"


class PlannerSpecError(ValueError):
    """A planner spec that does not give a planner: ``"{argument} {spec!r}: {reason}"``."""

    def __init__(self, argument: str, spec: object, reason: str) -> None:
        self.argument, self.spec, self.reason = argument, spec, reason
        super().__init__(f"{argument} {spec!r}: {reason}")

    def named(self, argument: str) -> str:
        """The message with the argument called ``argument`` (e.g. ``--planner``)."""
        return f"{argument} {self.spec!r}: {self.reason}"


def load_planner(
    spec: str, dynamics: DynamicsConfig | None = None, argument: str = "--planner"
) -> EgoPlanner:
    """A fresh planner from ``spec`` (module docstring).

    Args:
        spec: the planner spec.
        dynamics: the env's dynamics bounds, for the built-in planners that take them.
        argument: how the caller names the spec in error messages.

    Raises:
        PlannerSpecError: naming ``argument``: a malformed spec, a module or file that does
            not exist, an attribute that is not there, or an object that is not callable
            (or whose factory does not return a callable).
    """
    parts = check_spec(spec, argument)
    if parts is None:  # a built-in
        return make_planner(spec, dynamics)
    location, name = parts
    if location.endswith(".py") or "/" in location or "\\" in location:
        module = _module_from_file(Path(location), spec, argument)
    else:
        module = _module_from_import(location, spec, argument)
    if not hasattr(module, name):
        raise PlannerSpecError(
            argument, spec, f"{location} has no attribute {name!r}{_close_names(module, name)}"
        )
    return _as_planner(getattr(module, name), spec, argument)


def check_spec(spec: object, argument: str = "--planner") -> tuple[str, str] | None:
    """``(location, object)`` of a spec of one of the forms (module docstring), None for a
    built-in name; :class:`PlannerSpecError` naming ``argument`` for any other value. Reads
    the value alone: no module is imported, no file read (:func:`load_planner` does)."""
    if not isinstance(spec, str) or not spec.strip():
        raise PlannerSpecError(argument, spec, f"expected {_forms()}")
    if spec in PLANNERS:
        return None
    location, colon, name = spec.rpartition(":")
    if not colon or not location or not name.isidentifier():
        hint = did_you_mean(spec, PLANNERS)
        if not colon and spec.endswith(".py"):  # a file without the object to take from it
            hint = f" (name the planner in it: {spec}:OBJECT, e.g. {spec}:plan)"
        raise PlannerSpecError(argument, spec, f"expected {_forms()}{hint}")
    return location, name


def spec_of(planner: object) -> str | None:
    """A spec that loads ``planner`` again, when it is a module-level function, class or
    instance of a no-argument class: ``module:name``, or ``file.py:name`` for one defined
    in a script or a planner file; None when there is none."""
    if isinstance(planner, str):
        return planner
    target = planner if inspect.isfunction(planner) or inspect.isclass(planner) else type(planner)
    name, module_name = getattr(target, "__qualname__", ""), getattr(target, "__module__", "")
    module = sys.modules.get(module_name)
    if module is None or not name.isidentifier() or getattr(module, name, None) is not target:
        return None
    if module_name == "__main__" or module_name.startswith(FILE_MODULE_PREFIX):
        file = getattr(module, "__file__", None)
        return None if file is None else f"{_relative(Path(file))}:{name}"
    return f"{module_name}:{name}"


def _relative(path: Path) -> str:
    try:
        return path.resolve().relative_to(Path.cwd()).as_posix()
    except ValueError:
        return str(path)


def _forms() -> str:
    return FORMS.format(names=", ".join(PLANNERS))


def _module_from_import(location: str, spec: str, argument: str):
    try:
        return importlib.import_module(location)
    except ModuleNotFoundError as err:
        missing = err.name or ""
        if location == missing or location.startswith(missing + "."):
            raise PlannerSpecError(
                argument,
                spec,
                f"no module named {missing!r} (is it installed or on "
                "PYTHONPATH? a file is given as path/to/file.py:object)",
            ) from err
        raise PlannerSpecError(argument, spec, f"importing {location} failed: {err}") from err


def _module_from_file(path: Path, spec: str, argument: str):
    if path.suffix != ".py":
        raise PlannerSpecError(argument, spec, "a planner file must end in .py")
    if not path.is_file():
        raise PlannerSpecError(argument, spec, f"no such file {str(path)!r}")
    path = path.resolve()
    digest = hashlib.sha256(str(path).encode()).hexdigest()[:8]
    module_name = f"{FILE_MODULE_PREFIX}{path.stem}_{digest}"
    if module_name in sys.modules:  # loaded already: the same module, as import does
        return sys.modules[module_name]
    folder = str(path.parent)
    if folder not in sys.path:
        sys.path.insert(0, folder)
    module_spec = importlib.util.spec_from_file_location(module_name, path)
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[module_name] = module  # dataclasses and pickling look their module up
    try:
        module_spec.loader.exec_module(module)
    except Exception as err:
        sys.modules.pop(module_name, None)
        raise PlannerSpecError(
            argument, spec, f"running {path} failed: {type(err).__name__}: {err}"
        ) from err
    return module


def _as_planner(value: object, spec: str, argument: str) -> EgoPlanner:
    if not callable(value):
        raise PlannerSpecError(
            argument,
            spec,
            f"{type(value).__name__} object is not callable; expected a "
            "planner (observation, view) -> action, or a class or factory that returns one",
        )
    if inspect.isclass(value) or _takes_no_argument(value):
        try:
            value = value()
        except TypeError as err:
            raise PlannerSpecError(
                argument,
                spec,
                f"calling it with no argument failed ({err}); a class or "
                "factory must build the planner without arguments",
            ) from err
        if not callable(value):
            raise PlannerSpecError(
                argument,
                spec,
                f"it returned a {type(value).__name__}, which is not a "
                "callable planner (observation, view) -> action",
            )
    try:
        inspect.signature(value).bind(None, None)
    except TypeError as err:
        raise PlannerSpecError(
            argument, spec, f"it cannot be called as planner(observation, view): {err}"
        ) from err
    except ValueError:  # no signature to read (some builtins): let the first call tell
        pass
    return value


def _takes_no_argument(value: object) -> bool:
    """A function (or builtin) whose parameters all have defaults: a factory."""
    if not (inspect.isfunction(value) or inspect.ismethod(value)):
        return False
    try:
        parameters = inspect.signature(value).parameters.values()
    except (TypeError, ValueError):
        return False
    required = (
        p for p in parameters
        if p.default is inspect.Parameter.empty
        and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
    )  # fmt: skip
    return next(required, None) is None


def _close_names(module, name: str) -> str:
    values = {n: getattr(module, n) for n in dir(module) if not n.startswith("_")}
    names = [n for n, v in values.items() if callable(v) and not inspect.ismodule(v)]
    close = difflib.get_close_matches(name, names, n=3)
    return f" (did you mean {', '.join(close)}?)" if close else ""


__all__ = ["PlannerSpecError", "load_planner", "spec_of"]
