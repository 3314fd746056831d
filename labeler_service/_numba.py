"""The one place for numba options.

``njit`` compiles with ``cache=True`` (compile once per machine, not per process) and a fastmath
set that keeps NaN/inf semantics: a NaN is how a missing marker is spelled in this project, so
``nnan``/``ninf`` are never enabled.

numba's on-disk cache checks only the source file of each cached function: a kernel whose callee
in another file changed (an edit, an upgrade that rewrote some files) kept running its old
compiled code, silently. Here the project's kernels are cached under a stamp of *every* file
that holds kernels (:func:`kernel_sources`), so any change to one of them recompiles them all
once. This hooks numba's cache locators (``CacheImpl._locator_classes``, not a public API);
when a numba version lacks them, the default per-file check stays and :data:`SET_STAMPED` is
False.

numba caches a kernel beside its source (``__pycache__``), else in the user's cache folder
(``~/.cache/numba``); when neither is writable (a package installed read-only, run by a user
whose home is not writable) it refuses to decorate the kernel ("no locator available"). Then,
unless ``NUMBA_CACHE_DIR`` is set, the cache goes to a folder of this user's under the
temporary folder (:func:`_temp_cache_dir`): the first run compiles, the next ones read it.
"""

from __future__ import annotations

import hashlib
import logging
import os
import stat
import tempfile
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import Any

import numba
from numba.misc.appdirs import AppDirs

FASTMATH = frozenset({"nsz", "arcp", "contract", "afn", "reassoc"})
_PACKAGE = Path(__file__).resolve().parent
#: the folders whose modules define kernels (``labeling`` with ``kernels``, the simulator's)
_KERNEL_DIRS = (_PACKAGE / "labeling", _PACKAGE / "scenes" / "sim")
log = logging.getLogger(__name__)


def _writable(folder: Path) -> bool:
    """numba's own test of a cache folder (``_CacheLocator.ensure_cache_path``)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def _temp_cache_dir() -> Path:
    """``mocap-labeler-numba-<uid>`` under the temporary folder, created private; a folder of
    that name someone else owns or can write to is not used (numba's cache files are pickles):
    a new private folder is, for this run."""
    uid = os.getuid() if hasattr(os, "getuid") else None
    d = Path(tempfile.gettempdir()) / f"mocap-labeler-numba-{uid if uid is not None else 'user'}"
    try:  # (gettempdir raises when no temporary folder is usable: the caller says so)
        d.mkdir(mode=0o700, exist_ok=True)
        st = d.lstat()
        if (
            stat.S_ISDIR(st.st_mode)
            and (uid is None or st.st_uid == uid)
            and not st.st_mode & 0o022
            and _writable(d)
        ):
            return d
    except OSError:
        pass
    fresh = Path(tempfile.mkdtemp(prefix="mocap-labeler-numba-"))
    log.warning(
        "numba cache: %s is not this user's private folder; compiling into %s for this run "
        "(set NUMBA_CACHE_DIR to keep a cache)",
        d,
        fresh,
    )
    return fresh


def _kernel_dir_files() -> Iterator[Path]:
    """The ``.py`` files of :data:`_KERNEL_DIRS` (not their ``__pycache__``)."""
    for d in _KERNEL_DIRS:
        for p in d.rglob("*.py"):
            if "__pycache__" not in p.parts:
                yield p


def _cache_dir_fallback() -> str | None:
    """Points numba's cache at :func:`_temp_cache_dir` when ``NUMBA_CACHE_DIR`` is not set
    and neither the kernels' ``__pycache__`` folders nor numba's user-wide cache folder can be
    written; returns that folder (None: numba's own choice stands). Runs at import, before the
    first kernel is decorated (numba picks a kernel's cache folder then)."""
    config: Any = numba.config  # its settings are module globals set at run time
    if "NUMBA_CACHE_DIR" in os.environ or config.CACHE_DIR or config.DISABLE_JIT:
        return None
    if all(_writable(d / "__pycache__") for d in {p.parent for p in _kernel_dir_files()}):
        return None
    if _writable(Path(AppDirs(appname="numba", appauthor=False).user_cache_dir)):
        return None
    try:
        folder = str(_temp_cache_dir())
    except OSError as exc:  # no usable temporary folder either: numba's own error will say so
        log.warning("numba cache: no writable folder for compiled kernels (%s)", exc)
        return None
    os.environ["NUMBA_CACHE_DIR"] = folder  # read again by numba's compiler, and by children
    config.CACHE_DIR = folder
    log.info("numba cache: the package and the home folder are read-only: %s", folder)
    return folder


#: the cache folder chosen by :func:`_cache_dir_fallback`, None when numba's own stands
CACHE_DIR_FALLBACK = _cache_dir_fallback()


def njit(*args: Any, **kwargs: Any) -> Any:
    """``numba.njit`` with the project's defaults (``cache=True``, NaN-safe fastmath)."""
    kwargs.setdefault("cache", True)
    kwargs.setdefault("fastmath", set(FASTMATH))
    kwargs.setdefault("nogil", True)
    return numba.njit(*args, **kwargs)


def kernel_sources() -> list[Path]:
    """Every source file whose change must recompile the project's cached kernels: the files
    of a ``kernels`` folder (kernels, and the state types and constants they read) and every
    other file of :data:`_KERNEL_DIRS` that uses numba. A file without kernels (the booting
    wrapper, the trainer) recompiles nothing when it changes."""
    files = {Path(__file__).resolve()}
    for p in _kernel_dir_files():
        if "kernels" in p.parts or _uses_numba(p):
            files.add(p.resolve())
    return sorted(files)


def _uses_numba(p: Path) -> bool:
    text = p.read_text(encoding="utf-8", errors="replace")
    return "_numba import" in text or "import numba" in text or "from numba" in text


@cache
def kernel_set_stamp() -> str:
    """A hash of :func:`kernel_sources` (their bytes) and the numba version."""
    h = hashlib.sha256(numba.__version__.encode())
    for p in kernel_sources():
        h.update((str(p.relative_to(_PACKAGE)) if p.is_relative_to(_PACKAGE) else p.name).encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def _in_package(py_file: str) -> bool:
    try:
        return Path(py_file).resolve().is_relative_to(_PACKAGE)
    except (OSError, ValueError):
        return False


def _stamp_locators() -> bool:
    """Puts a set-stamped twin before each of numba's source-file cache locators (for the
    project's files only). Returns False when this numba has no such hook."""
    try:
        from numba.core import caching

        impl = caching.CacheImpl
        bases = [
            c for c in impl._locator_classes
            if issubclass(c, caching._SourceFileBackedLocatorMixin)
        ]  # fmt: skip
    except (ImportError, AttributeError):
        return False
    if not bases or any(getattr(c, "_mocap_stamped", False) for c in impl._locator_classes):
        return bool(bases)
    out: list[Any] = []
    for c in impl._locator_classes:
        if c in bases:

            def from_function(cls, py_func, py_file):
                if not _in_package(py_file):
                    return None
                return super(cls, cls).from_function.__func__(cls, py_func, py_file)

            def get_source_stamp(self, _base=c):
                return (_base.get_source_stamp(self), kernel_set_stamp())

            twin = type(
                f"SetStamped{c.__name__}",
                (c,),
                {
                    "_mocap_stamped": True,
                    "from_function": classmethod(from_function),
                    "get_source_stamp": get_source_stamp,
                },
            )
            out.append(twin)
        out.append(c)
    impl._locator_classes = out
    return True


#: True when the project's kernels are cached under the stamp of the whole kernel set
SET_STAMPED = _stamp_locators()
