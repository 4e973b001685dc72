"""The code a run's numbers come from, as one hash (:func:`code_fingerprint`).

Every run records it in its ``manifest.json`` (``code_fingerprint``), and every record of the results book carries
the fingerprint of the run it was made from: a record whose fingerprint is not the checkout's was made by code that
may have changed its results, so the book treats it as stale and runs that job again. The hash covers every Python
file of the package except the parts that only present results (:data:`PRESENTATION`: the command line, the
report, the book, the benchmarks), so rewording a table does not throw away hours of runs, while any change to the
front end, the network, the training or the metrics does. A run's config is not in it: the book hashes the config
of each grid on its own.
"""

from __future__ import annotations

import hashlib
from functools import lru_cache
from pathlib import Path

#: The package's root folder.
PACKAGE = Path(__file__).resolve().parent.parent
#: Subpackages that only present results; a change there does not change a run's numbers.
PRESENTATION = ("cli", "report", "book", "bench")


def code_files(root: Path = PACKAGE) -> list[Path]:
    """The package's Python files that make a run's numbers (module docstring), sorted by relative path."""
    files = []
    for p in root.rglob("*.py"):
        rel = p.relative_to(root).parts
        if rel[0] in PRESENTATION or "__pycache__" in rel:
            continue
        files.append(p)
    return sorted(files, key=lambda p: p.relative_to(root).as_posix())


def code_manifest(root: Path = PACKAGE) -> dict[str, str]:
    """Relative path → SHA-256 (16 hex digits) of each of :func:`code_files`; line endings normalised."""
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes().replace(b"\r\n", b"\n")).hexdigest()[:16]
            for p in code_files(root)}


def fingerprint_of(manifest: dict[str, str]) -> str:
    """The fingerprint (16 hex digits) of a :func:`code_manifest`."""
    text = "\n".join(f"{k} {v}" for k, v in sorted(manifest.items()))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """This checkout's fingerprint (computed once per process).

    >>> len(code_fingerprint())
    16
    """
    return fingerprint_of(code_manifest())


def changed_files(old: dict[str, str], new: dict[str, str]) -> list[str]:
    """The files added, removed or changed from manifest ``old`` to ``new``, sorted.

    >>> changed_files({"a.py": "1", "b.py": "2"}, {"a.py": "1", "b.py": "3", "c.py": "4"})
    ['b.py', 'c.py']
    """
    return sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
