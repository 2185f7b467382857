"""Package metadata: version from the installed metadata, the typing marker shipped with the sources."""

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
