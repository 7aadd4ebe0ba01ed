"""A folder the gateway cannot write to, whoever runs the tests: root writes through
any mode bits, so for root it is a read-only file system (a tmpfs mounted, filled,
then remounted read-only), for anyone else read-only by its mode."""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Iterator, Mapping
from pathlib import Path


@contextlib.contextmanager
def read_only(folder: Path, files: Mapping[str, str] | None = None) -> Iterator[None]:
    """``folder`` (made here) holding ``files`` (name → text), read-only inside."""
    folder.mkdir()
    root = os.geteuid() == 0
    if root:
        subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(folder)],
                       check=True)
    try:
        for name, text in (files or {}).items():
            (folder / name).write_text(text)
            if not root:
                (folder / name).chmod(0o444)
        if root:
            subprocess.run(["mount", "-o", "remount,ro", str(folder)], check=True)
        else:
            folder.chmod(0o555)
        yield
    finally:
        if root:
            subprocess.run(["umount", str(folder)], check=True)
        else:
            folder.chmod(0o755)
