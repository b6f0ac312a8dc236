"""Write a file so that readers see either the old file or the complete new one, never a part.

Takes a destination path and a writer callback (and a check, given the temporary file's path
once it is written, which may still change it; and ``opened``, given that path before the writer
starts); writes a temporary file beside the destination,
flushes it to disk, renames it over the destination (keeping an existing file's permissions and,
where allowed, its owner; through a symbolic link, the file it points to is replaced) and
flushes the directory, so the rename survives a power cut. On any error, or an interrupt, the
temporary file is removed and the destination is untouched; an ``OSError`` names the destination
(``filename``) and says what failed (``strerror``: ``cannot write: ...``).
"""
from __future__ import annotations

import os
import secrets
from collections.abc import Callable
from pathlib import Path
from typing import IO


def atomic_write(path: str | Path, write: Callable[[IO[bytes]], None],
                 check: Callable[[Path], None] | None = None, opened: Callable[[Path], None] | None = None) -> None:
    path = Path(os.path.realpath(path))
    try:
        _replace(path, write, check, opened)
    except OSError as exc:
        raise OSError(exc.errno, f"cannot write: {exc.strerror or exc}", str(path)) from None


def _replace(path: Path, write: Callable[[IO[bytes]], None], check: Callable[[Path], None] | None,
             opened: Callable[[Path], None] | None) -> None:
    tmp = None
    try:
        # (named before it is made, so that an interrupt while it is made still finds it)
        while tmp is None:
            tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
            try:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o600)
            except FileExistsError:  # (another writer's: not ours to remove)
                tmp = None
        with os.fdopen(fd, "wb") as f:
            if opened is not None:
                opened(Path(tmp))
            write(f)
            f.flush()
        if check is not None:
            check(Path(tmp))
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        try:
            old = path.stat()
        except FileNotFoundError:
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)
        else:
            if (old.st_uid, old.st_gid) != (os.geteuid(), os.getegid()):
                try:  # a print server running as root must not take the user's file
                    os.chown(tmp, old.st_uid, old.st_gid)
                except PermissionError:
                    pass
            os.chmod(tmp, old.st_mode & 0o7777)  # after chown, which clears set-id bits
        os.replace(tmp, path)
    except BaseException:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
        raise
    _sync_directory(path.parent)


def _sync_directory(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # not every platform opens directories
        return
    try:
        os.fsync(fd)
    except OSError:  # nor syncs them
        pass
    finally:
        os.close(fd)
