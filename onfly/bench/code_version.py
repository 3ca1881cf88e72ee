"""Which code flew an episode: a digest of the code's files and the git commit.

A benchmark folder resumes by episode keys that name the config, not the code; the records
carry this version so that a rerun after a code change does not mix two versions in one
table unless asked (``onfly bench --allow-mixed-code``), and the tables of record
(``experiments/tables_of_record.py``) keep one version per table the same way.
"""

from __future__ import annotations

import hashlib
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

__all__ = ["CODE_PATHS", "REPO", "CodeVersion", "code_digest", "code_version"]

#: The repository (or, installed, the folder holding the ``onfly`` package).
REPO = Path(__file__).resolve().parents[2]
#: Folders (relative to the repository) whose tracked files make the code digest.
CODE_PATHS = ("onfly", "planning", "vlm", "experiments/configs")


@dataclass(frozen=True)
class CodeVersion:
    """The code that flies episodes: a content digest (16 hex digits) and the commit
    (``git rev-parse HEAD``, ``-dirty`` when a tracked file under :data:`CODE_PATHS` differs
    from it; ``unknown`` outside a git work tree)."""

    digest: str
    commit: str

    def as_dict(self) -> dict:
        return {"digest": self.digest, "commit": self.commit}


def _git(root: Path, *args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=root, capture_output=True, check=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.decode("utf-8", "surrogateescape")


def _code_files(root: Path, paths: Sequence[str]) -> list[str]:
    """Tracked files under ``paths`` (every file there outside a git work tree), sorted."""
    listed = _git(root, "ls-files", "-z", "--", *paths)
    if listed is not None:
        return sorted(f for f in listed.split("\0") if f)
    files = []
    for p in paths:
        for f in (root / p).rglob("*"):
            if f.is_file() and "__pycache__" not in f.parts:
                files.append(f.relative_to(root).as_posix())
    return sorted(files)


def code_digest(root: str | Path = REPO, paths: Sequence[str] = CODE_PATHS) -> str:
    """SHA-256 (first 16 hex digits) over the path and on-disk content of every tracked file
    under ``paths`` (a deleted tracked file counts as deleted)."""
    root = Path(root)
    h = hashlib.sha256()
    for rel in _code_files(root, paths):
        f = root / rel
        h.update(rel.encode("utf-8", "surrogateescape") + b"\0")
        h.update(hashlib.sha256(f.read_bytes()).digest() if f.is_file() else b"<deleted>")
    return h.hexdigest()[:16]


def code_version(root: str | Path = REPO, paths: Sequence[str] = CODE_PATHS) -> CodeVersion:
    """The code's digest and commit (see :class:`CodeVersion`)."""
    root = Path(root)
    head = _git(root, "rev-parse", "HEAD")
    if head is None:
        return CodeVersion(code_digest(root, paths), "unknown")
    status = _git(root, "status", "--porcelain", "--untracked-files=no", "--", *paths) or ""
    return CodeVersion(code_digest(root, paths), head.strip() + ("-dirty" if status.strip() else ""))
