"""Atomic output: write to a temporary file in the destination folder, then rename.

A reader therefore sees either no file, the previous complete file, or the new complete file,
never a truncated one, even if the process is killed mid-write. A process killed mid-write
leaves its hidden temporary file (``.<name>.<pid>.<random>.part``) behind; the next write of
the same output removes those whose process has ended.
"""

from __future__ import annotations

import contextlib
import glob
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

#: For tests only: the name of an output file. Writing a file of that name pauses
#: :data:`PAUSE_S` seconds once its data are in the temporary file, before the rename, after
#: saying so on stderr, so that a test can kill the writer there.
PAUSE_ENV = "LATENTZ_TEST_PAUSE_WRITING"
PAUSE_S = 60.0


def _process_ended(pid: int) -> bool:
    """True when no process ``pid`` runs (POSIX; elsewhere never claimed)."""
    if os.name != "posix":
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False


def _remove_orphans(target: Path) -> None:
    """Remove temporary files of ``target`` left by writers that were killed."""
    prefix = f".{target.name}."
    for part in target.parent.glob(glob.escape(prefix) + "*.part"):
        pid = part.name[len(prefix) :].split(".", 1)[0]
        if pid.isdigit() and _process_ended(int(pid)):
            part.unlink(missing_ok=True)


def _pause_for_tests(target: Path, tmp: Path) -> None:
    if os.environ.get(PAUSE_ENV) == target.name:
        print(f"latentz: paused writing {target} in {tmp.name}", file=sys.stderr, flush=True)
        time.sleep(PAUSE_S)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success, fsync and rename it onto ``path``.

    On any exception the temporary file is removed and ``path`` is left untouched.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    _remove_orphans(target)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{target.name}.{os.getpid()}.", suffix=".part", dir=target.parent
    )
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file the usual permissions
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        _pause_for_tests(target, tmp_path)
        with open(tmp_path, "rb+") as handle:
            os.fsync(handle.fileno())
        os.replace(tmp_path, target)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    write_bytes_atomic(path, text.encode("utf-8"))
