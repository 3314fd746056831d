"""``make mutants``: a curated mutation check -- do the tests catch small deliberate bugs?

Each mutant (the ``MUTANTS`` list in ``scripts/mutant_list.py``) is one exact source-snippet
replacement. For every mutant the tree (``labeler_service``, ``offline``, ``tests``,
``pyproject.toml``) is copied to a temporary folder, the snippet is replaced there (never in
place), and only the tests that should catch it run (``pytest -x`` with a timeout) with the
copy first on ``PYTHONPATH``. A mutant is **killed** when those tests fail (or time out),
**survived** when they pass, and **stale** when its snippet is not found exactly once: code
changed by someone else shows up loudly instead of passing silently; refresh the snippet.

numba: the copies keep the ``__pycache__`` folders with their mtimes, so the kernels' on-disk
cache stays valid (``warm_up`` fills it first). A mutant of a kernel file (``kernel=True``)
drops every numba cache of its copy: ``cache=True`` does not notice an edited callee in
another file, so the whole kernel set is compiled afresh for it.

Prints one JSON line: ``{"mutants": N, "killed": K, "survived": [...], "stale": [...],
"seconds": S}``; progress goes to stderr. Exits 1 when fewer than 90 % are killed or a snippet
is stale. ``--list`` shows the mutants, ``--only NAME...`` runs
some, ``--jobs`` sets the parallel runs (default 2), ``--keep`` leaves the copies for a look.

    .venv/bin/python scripts/mutants.py
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

from mutant_list import MUTANTS, Mutant  # noqa: E402

COPY = ("labeler_service", "offline", "tests", "benchmarks", "pyproject.toml")
NUMBA_CACHE_SUFFIXES = (".nbi", ".nbc")


def warm_up() -> float:
    """Compiles (or loads) every labeling kernel into the source tree's numba cache."""
    t0 = time.perf_counter()
    code = (
        "from labeler_service.labeling.config import LabelerConfig\n"
        "from labeler_service.service.server import warm_up\n"
        "warm_up('online', LabelerConfig())\n"
    )
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, env=_env(ROOT))
    return time.perf_counter() - t0


def _env(tree: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(tree), str(tree / "tests")])
    env.pop("NUMBA_CACHE_DIR", None)  # in-tree caches (next to the sources) travel with a copy
    env.pop("NUMBA_DISABLE_JIT", None)
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    real = (ROOT / ".." / "shared" / "data" / "real").resolve()
    if "MOCAP_DATA_DIR" not in env and real.is_dir():
        # (a copy in a temporary folder has no ../shared beside it: real-data tests skipped,
        # and a mutant only they catch survived)
        env["MOCAP_DATA_DIR"] = str(real)
    return env


def _ignore(_dir: str, names: list[str]) -> set[str]:
    return {n for n in names if n in (".pytest_cache", ".hypothesis", "reports")}


def make_tree(dest: Path) -> None:
    for name in COPY:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=_ignore, copy_function=shutil.copy2)
        else:
            shutil.copy2(src, dest / name)


def apply(tree: Path, m: Mutant) -> int:
    """Replaces the snippet in the copy; returns how often it occurred (1 = applied)."""
    path = tree / m.file
    text = path.read_text(encoding="utf-8")
    n = text.count(m.old)
    if n == 1:
        path.write_text(text.replace(m.old, m.new), encoding="utf-8")
    return n


def drop_numba_cache(tree: Path) -> None:
    for p in tree.rglob("*"):
        if p.suffix in NUMBA_CACHE_SUFFIXES:
            p.unlink()


def run_one(m: Mutant, base: Path, timeout: float, keep: bool) -> tuple[str, str]:
    """``(outcome, detail)`` with outcome ``killed``, ``survived`` or ``stale``."""
    tree = Path(tempfile.mkdtemp(prefix=f"{m.name}-", dir=base))
    t0 = time.perf_counter()
    try:
        make_tree(tree)
        n = apply(tree, m)
        if n != 1:
            return "stale", f"snippet found {n} times in {m.file}"
        if m.kernel:
            drop_numba_cache(tree)
        cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
               f"--timeout={int(timeout)}", "-o", "addopts=--strict-markers "
               "--import-mode=importlib", *m.tests]  # fmt: skip
        if m.k:
            cmd += ["-k", m.k]
        try:
            proc = subprocess.run(cmd, cwd=tree, env=_env(tree), capture_output=True, text=True,
                                  timeout=timeout + 60)  # fmt: skip
        except subprocess.TimeoutExpired:
            return "killed", f"timed out after {timeout + 60:.0f} s"
        tail = (proc.stdout.strip().splitlines() or [""])[-1]
        if proc.returncode == 0:
            return "survived", tail
        if proc.returncode in (1, 3):  # tests failed / internal error raised by the mutant
            return "killed", tail
        # 2 interrupted (e.g. collection error), 4 usage error, 5 no tests: the mutant
        # made the tests unusable, or the selection is wrong -- say so loudly
        return (
            "killed" if proc.returncode == 2 else "stale",
            f"pytest exit {proc.returncode}: {tail}",
        )
    finally:
        took = time.perf_counter() - t0
        print(f"  {m.name}: {took:.0f} s", file=sys.stderr, flush=True)
        if not keep:
            shutil.rmtree(tree, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--only", nargs="+", default=None, metavar="NAME")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--timeout", type=float, default=240.0, help="pytest timeout per test (s)")
    p.add_argument("--list", action="store_true")
    p.add_argument("--keep", action="store_true", help="keep the mutated copies")
    args = p.parse_args(argv)
    names = [m.name for m in MUTANTS]
    if len(set(names)) != len(names):
        raise SystemExit("duplicate mutant names")
    chosen = [m for m in MUTANTS if args.only is None or m.name in args.only]
    if args.only and len(chosen) != len(set(args.only)):
        raise SystemExit(f"unknown mutant(s): {sorted(set(args.only) - set(names))}")
    if args.list:
        for m in chosen:
            print(f"{m.name:40s} {m.file}  [{', '.join(m.tests)}]  {m.why}")
        return 0
    t0 = time.perf_counter()
    print(f"warming the numba cache ({warm_up():.0f} s)", file=sys.stderr, flush=True)
    base = Path(tempfile.mkdtemp(prefix="mutants-"))
    results: dict[str, tuple[str, str]] = {}
    try:
        with ThreadPoolExecutor(max(1, args.jobs)) as pool:
            futures = {m.name: pool.submit(run_one, m, base, args.timeout, args.keep)
                       for m in chosen}  # fmt: skip
            for name, fut in futures.items():
                results[name] = fut.result()
                outcome, detail = results[name]
                print(f"{outcome:9s} {name}: {detail}", file=sys.stderr, flush=True)
    finally:
        if not args.keep:
            shutil.rmtree(base, ignore_errors=True)
    out = {
        "mutants": len(chosen),
        "killed": sum(o == "killed" for o, _ in results.values()),
        "survived": [n for n, (o, _) in results.items() if o == "survived"],
        "stale": [n for n, (o, _) in results.items() if o == "stale"],
        "seconds": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(out))
    # a check, not only a report: too many survivors or any stale snippet fails make mutants
    return 0 if out["killed"] >= 0.9 * len(chosen) and not out["stale"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
