"""numba's cache and an edited callee in another file (``labeler_service._numba``).

``cache=True`` checks only the cached function's own source file: a kernel whose callee in
another file changed kept its old compiled code. The project's kernels are cached under a stamp
of every kernel file, so the caller recompiles. Where numba's default cache folders cannot be
written, the cache goes to a private folder under the temporary folder (unless
``NUMBA_CACHE_DIR`` says where)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from labeler_service import _numba

ROOT = Path(__file__).resolve().parents[1]
CALLEE = "from labeler_service._numba import njit\n\n\n@njit\ndef g():\n    return {}\n"
CALLER = (
    "from labeler_service._numba import njit\n"
    "from labeler_service.labeling.kernels.zz_callee import g\n\n\n"
    "@njit\ndef f():\n    return g() + 100\n"
)
DEFAULT_ONLY = (  # the negative control: numba's own per-file check
    "from numba.core import caching\n"
    "import labeler_service._numba\n"
    "caching.CacheImpl._locator_classes = [c for c in caching.CacheImpl._locator_classes\n"
    "    if not getattr(c, '_mocap_stamped', False)]\n"
)


def _run(tree: Path, prelude: str = "") -> int:
    code = prelude + "from labeler_service.labeling.kernels.zz_caller import f\nprint(f())\n"
    env = {**os.environ, "PYTHONPATH": str(tree), "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("NUMBA_DISABLE_JIT", None)
    out = subprocess.run([sys.executable, "-c", code], cwd=tree, env=env, check=True,
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    return int(out.stdout.split()[-1])


def _edit_callee(kernels: Path, value: int) -> None:
    p = kernels / "zz_callee.py"
    p.write_text(CALLEE.format(value))
    st = p.stat()
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 2_000_000_000))


@pytest.mark.parametrize("stamped", [True, False])
def test_a_kernel_recompiles_when_its_callee_in_another_file_changes(tmp_path, stamped):
    assert _numba.SET_STAMPED  # this numba has the locator hook
    tree = tmp_path / "tree"
    shutil.copytree(ROOT / "labeler_service", tree / "labeler_service",
                    ignore=shutil.ignore_patterns("__pycache__", "static"))  # fmt: skip
    kernels = tree / "labeler_service" / "labeling" / "kernels"
    (kernels / "zz_caller.py").write_text(CALLER)
    _edit_callee(kernels, 1)
    prelude = "" if stamped else DEFAULT_ONLY
    assert _run(tree, prelude) == 101
    assert any(kernels.glob("__pycache__/zz_caller*.nbi"))  # cached on disk
    _edit_callee(kernels, 2)
    # numba's own check alone runs the caller's old code (the stale class this removes)
    assert _run(tree, prelude) == (102 if stamped else 101)


def test_the_stamp_covers_every_kernel_file(tmp_path, monkeypatch):
    files = _numba.kernel_sources()
    names = {p.name for p in files}
    assert {"_numba.py", "step.py", "contact.py", "labeler.py", "occlusion.py"} <= names
    d = tmp_path / "labeling"
    d.mkdir()
    (d / "a.py").write_text("from labeler_service._numba import njit\nX = 1\n")
    (d / "plain.py").write_text("Y = 1\n")  # no kernels: no recompile when it changes
    monkeypatch.setattr(_numba, "_KERNEL_DIRS", (d,))
    _numba.kernel_set_stamp.cache_clear()
    try:
        before = _numba.kernel_set_stamp()
        (d / "plain.py").write_text("Y = 2\n")
        _numba.kernel_set_stamp.cache_clear()
        assert _numba.kernel_set_stamp() == before
        (d / "a.py").write_text("from labeler_service._numba import njit\nX = 2\n")
        _numba.kernel_set_stamp.cache_clear()
        assert _numba.kernel_set_stamp() != before
    finally:
        _numba.kernel_set_stamp.cache_clear()


def _no_default_cache(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    """A copy of the package where numba's default cache folders cannot be written, even by
    root: each source folder's ``__pycache__`` and the home and XDG cache folders are files
    (a package installed read-only, run by a user whose home is not writable)."""
    tree = tmp_path / "tree"
    shutil.copytree(ROOT / "labeler_service", tree / "labeler_service",
                    ignore=shutil.ignore_patterns("__pycache__", "static"))  # fmt: skip
    for d in [tree / "labeler_service", *(tree / "labeler_service").rglob("*")]:
        if d.is_dir():
            (d / "__pycache__").write_text("")
    blocked = tmp_path / "blocked"
    blocked.write_text("")
    (tmp_path / "tmp").mkdir()
    env = {
        **os.environ,
        "PYTHONPATH": str(tree),
        "PYTHONDONTWRITEBYTECODE": "1",
        "HOME": str(blocked),
        "XDG_CACHE_HOME": str(blocked),
        "TMPDIR": str(tmp_path / "tmp"),
    }
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("NUMBA_DISABLE_JIT", None)
    return tree, env


def _simulate(tree: Path, env: dict[str, str], out: Path) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "labeler_service.cli.main", "simulate", str(out),
           "--performers", "1", "--seconds", "1", "--scenario", "walk", "--seed", "1"]  # fmt: skip
    return subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=300)


def test_a_command_runs_when_no_default_cache_folder_is_writable(tmp_path):
    tree, env = _no_default_cache(tmp_path)
    done = _simulate(tree, env, tmp_path / "scene.npz")
    # numba alone: "cannot cache function ...: no locator available for file ...", a traceback
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert (tmp_path / "scene.npz").is_file()
    folder = tmp_path / "tmp" / f"mocap-labeler-numba-{os.getuid()}"
    assert any(folder.rglob("*.nbi"))  # cached there: the next run reads it


def test_a_numba_cache_dir_the_user_set_is_kept(tmp_path):
    tree, env = _no_default_cache(tmp_path)
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "mine")
    done = _simulate(tree, env, tmp_path / "scene.npz")
    assert done.returncode == 0, done.stderr
    assert any((tmp_path / "mine").rglob("*.nbi"))
    assert not list((tmp_path / "tmp").glob("mocap-labeler-numba-*"))


def test_a_temp_cache_folder_others_can_write_is_not_used(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    mine = _numba._temp_cache_dir()
    assert mine == tmp_path / f"mocap-labeler-numba-{os.getuid()}"
    assert mine.stat().st_mode & 0o777 == 0o700
    mine.chmod(0o777)  # planted, or opened up: numba's cache files are pickles
    other = _numba._temp_cache_dir()
    assert other != mine and other.parent == tmp_path
    assert other.stat().st_mode & 0o777 == 0o700


def test_no_usable_temp_folder_leaves_numba_its_own_choice(monkeypatch, caplog):
    """A review: with no writable cache folder and no usable temporary folder either, importing
    the package died of tempfile's ``FileNotFoundError`` instead of reaching numba's own words."""
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setattr(_numba.numba.config, "CACHE_DIR", "")
    monkeypatch.setattr(_numba, "_writable", lambda folder: False)

    def no_temp() -> str:
        raise FileNotFoundError("No usable temporary directory found")

    monkeypatch.setattr(tempfile, "gettempdir", no_temp)
    with caplog.at_level("WARNING", logger=_numba.__name__):
        assert _numba._cache_dir_fallback() is None
    assert "no writable folder for compiled kernels" in caplog.text
    assert "NUMBA_CACHE_DIR" not in os.environ
