"""Package metadata: version from the installed metadata, the typing marker shipped with the sources."""

import importlib
import inspect
import pkgutil
from importlib import metadata
from pathlib import Path

import pytest

import gmjax


def test_version_is_the_installed_metadata_version():
    try:
        expected = metadata.version("gmjax")
    except metadata.PackageNotFoundError:
        pytest.skip("gmjax is not installed (running from a bare source tree)")
    assert gmjax.__version__ == expected


def test_py_typed_marker_is_in_the_package():
    assert (Path(gmjax.__file__).parent / "py.typed").is_file()


def _public_modules():
    names = [
        m.name
        for m in pkgutil.walk_packages(gmjax.__path__, "gmjax.")
        if not any(part.startswith("_") for part in m.name.split(".")) and m.name != "gmjax.cli"
    ]
    return ["gmjax", *names]


def _public_callables():
    """Every function a public module exports (``__all__``, else its public names), and the public
    methods (plus ``__call__``) of every gmjax class it exports, once each."""
    seen = {}
    for module_name in _public_modules():
        module = importlib.import_module(module_name)
        names = getattr(module, "__all__", None) or [n for n in vars(module) if not n.startswith("_")]
        for name in names:
            obj = getattr(module, name)
            if inspect.isfunction(obj) and obj.__module__.startswith("gmjax"):
                seen[f"{obj.__module__}.{obj.__qualname__}"] = obj
            elif inspect.isclass(obj) and obj.__module__.startswith("gmjax"):
                for attr, member in vars(obj).items():
                    if attr.startswith("_") and attr != "__call__":
                        continue
                    if isinstance(member, (classmethod, staticmethod)):
                        member = member.__func__
                    if inspect.isfunction(member):
                        seen[f"{obj.__module__}.{obj.__qualname__}.{attr}"] = member
    return seen


def test_public_api_is_fully_annotated():
    """Every argument and the return of every exported function and public method is annotated (mypy in
    CI checks the annotations against the code)."""
    callables = _public_callables()
    assert len(callables) > 200  # the walk found the API
    missing = {}
    for qualname, fn in callables.items():
        sig = inspect.signature(fn)
        args = [
            p
            for p, v in sig.parameters.items()
            if v.annotation is inspect.Parameter.empty and p not in ("self", "cls")
        ]
        if args or sig.return_annotation is inspect.Signature.empty:
            missing[qualname] = args + (
                ["return"] if sig.return_annotation is inspect.Signature.empty else []
            )
    assert not missing, f"{len(missing)} public callables lack annotations: {missing}"
