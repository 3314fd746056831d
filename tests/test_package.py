"""The package surface: cheap import, lazy public re-exports, one version, py.typed."""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys
from pathlib import Path

import labeler_service


def _modules_after(code: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", f"{code}\nimport sys; print(' '.join(sys.modules))"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    return set(out.stdout.split())


def test_import_and_help_do_not_load_numba_or_matplotlib():
    for code in (
        "import labeler_service",
        "import labeler_service.cli.main as m\ntry:\n    m.main(['--help'])\nexcept SystemExit:\n"
        "    pass",
    ):
        loaded = _modules_after(code)
        assert "numba" not in loaded, code
        assert "matplotlib" not in loaded, code


def test_every_name_in_all_resolves_and_dir_lists_them():
    assert set(labeler_service.__all__) == {"__version__", *labeler_service._EXPORTS}
    for name in labeler_service.__all__:
        assert getattr(labeler_service, name) is not None, name
    assert set(labeler_service.__all__) <= set(dir(labeler_service))


def test_unknown_attribute_is_an_attribute_error():
    try:
        labeler_service.no_such_name  # noqa: B018
    except AttributeError as exc:
        assert "no_such_name" in str(exc)
    else:
        raise AssertionError("expected AttributeError")


def test_version_comes_from_the_distribution_metadata():
    assert labeler_service.__version__ == importlib.metadata.version("mocap-labeler")


def test_py_typed_marker_ships_with_the_package():
    assert (Path(labeler_service.__file__).parent / "py.typed").is_file()
