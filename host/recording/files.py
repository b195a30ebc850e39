"""The recording's on-disk names and the few file-system calls the writer makes.

`FileSystem` is the writer's only way to the disk, so that a test can make it fail the way a
disk does (ENOSPC part way through a write, EROFS, a write that never returns) without root,
mounts or a real full disk; the production class is a thin layer over `os`.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

SUFFIX = ".orec"
FILE_RE = re.compile(r"^orbitar-(\d{6})" + re.escape(SUFFIX) + "$")
FILE_MODE = 0o640


class FileSystem:
    """The OS calls of the writer thread (a test subclass injects failures)."""

    def makedirs(self, path: Path) -> None:
        """Create the directory and its parents."""
        os.makedirs(path, exist_ok=True)

    def listdir(self, path: Path) -> list[str]:
        """Names in a directory."""
        return os.listdir(path)

    def create(self, path: Path) -> int:
        """A new file for writing (it must not exist yet)."""
        return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, FILE_MODE)

    def write(self, fd: int, data: memoryview) -> int:
        """Write some of `data`; the count written."""
        return os.write(fd, data)

    def truncate(self, fd: int, size: int) -> None:
        """Cut the file back to `size` bytes (drop a partly written record)."""
        os.ftruncate(fd, size)

    def linked(self, fd: int) -> bool:
        """False once the open file was deleted (it would never be seen again)."""
        return os.fstat(fd).st_nlink > 0

    def close(self, fd: int) -> None:
        """Close the file."""
        os.close(fd)

    def unlink(self, path: Path) -> None:
        """Delete a file."""
        os.unlink(path)


def recording_paths(directory: Path, fs: FileSystem | None = None) -> list[Path]:
    """`orbitar-NNNNNN.orec` files in a directory, in number order ([] if it is not there)."""
    try:
        names = [n for n in (fs or FileSystem()).listdir(directory) if FILE_RE.match(n)]
    except (FileNotFoundError, NotADirectoryError):
        return []
    return [directory / n for n in sorted(names)]


def file_number(path: Path) -> int:
    """NNNNNN of orbitar-NNNNNN.orec (0 for any other name)."""
    match = FILE_RE.match(path.name)
    return int(match.group(1)) if match else 0


def file_name(number: int) -> str:
    """The name of recording file `number`."""
    return f"orbitar-{number:06d}{SUFFIX}"
