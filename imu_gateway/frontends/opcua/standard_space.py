"""asyncua's standard address space, kept on disk between starts (docs/deployment.md,
"Small boxes").

asyncua builds the OPC UA standard address space (some 20 000 nodes) in memory at each
start: 1.2 s and 50 MB on the development VM, several times that time on a small box.
Its own option for slow devices is a shelf: the nodes pickled into a dbm file once,
each loaded when first used.  The gateway builds it in a child process, so the
gateway itself never holds the whole space, and keeps it in its cache folder,
``$CACHE_DIRECTORY`` (systemd's ``CacheDirectory=``), else ``$XDG_CACHE_HOME`` or
``~/.cache``, under ``imu-gateway/``.

The shelf is named by asyncua's and Python's versions (an upgrade builds a new one) and
built in a temporary folder renamed into place when whole, so a start never reads half
of one.  If it cannot be built or kept, the space is built in memory as before: a
cache never stops the server.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import shutil
import sys
import tempfile
from importlib.metadata import version
from pathlib import Path

log = logging.getLogger("imu_gateway.opcua")

PREFIX = "opcua-standard-space-"
BUILD_TIMEOUT_S = 300.0  # a Pi Zero takes a while; the server waits for it once
#: the child: asyncua's own ``init`` with a shelf path that does not exist yet builds
#: the space and writes the shelf there
_BUILD = ("import asyncio, pathlib, sys, asyncua; "
          "asyncio.run(asyncua.Server().init(pathlib.Path(sys.argv[1])))")


def cache_folder() -> Path | None:
    """Where the gateway keeps what it can rebuild; None: no home to keep it in."""
    if os.environ.get("CACHE_DIRECTORY"):  # systemd's, possibly several, ':'-separated
        return Path(os.environ["CACHE_DIRECTORY"].split(":")[0])
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"]) / "imu-gateway"
    try:
        return Path.home() / ".cache" / "imu-gateway"
    except RuntimeError:  # no HOME and no passwd entry
        return None


async def shelf() -> Path | None:
    """The shelf for ``asyncua.Server.init``, built now if needed; None: build the
    space in memory (the reason is logged)."""
    folder = cache_folder()
    if folder is None:
        return None
    name = f"{PREFIX}{version('asyncua')}-py{sys.version_info[0]}.{sys.version_info[1]}"
    final = folder / name
    if not final.is_dir():
        try:
            await _build(folder, final)
        except (OSError, RuntimeError, TimeoutError) as exc:
            log.warning("OPC UA: the standard address space is built in memory (50 MB "
                        "more): its cache in %s could not be made: %s", folder, exc)
            return None
    return final / "space"


async def _build(folder: Path, final: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob(f"{PREFIX}*"):  # an earlier version's
        if old != final:
            shutil.rmtree(old, ignore_errors=True)
    log.info("OPC UA: building the standard address space's cache in %s (once)", folder)
    building = Path(tempfile.mkdtemp(prefix=".building-", dir=folder))
    try:
        child = await asyncio.create_subprocess_exec(
            sys.executable, "-c", _BUILD, str(building / "space"),
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
        try:
            async with asyncio.timeout(BUILD_TIMEOUT_S):
                _, err = await child.communicate()
        except TimeoutError:
            child.kill()
            await child.wait()
            raise
        if child.returncode != 0:
            said = err.decode(errors="replace").strip().splitlines()
            raise RuntimeError(said[-1] if said else f"exit status {child.returncode}")
        # asyncua finds a shelf by its path (dbm.gnu's file) or path.db (dbm.ndbm);
        # Python's fallback, dbm.dumb, writes space.dat and space.dir: an empty
        # "space" tells asyncua it is there (dbm itself tells the formats apart)
        (building / "space").touch()
        with contextlib.suppress(OSError):  # another gateway was first: its is as good
            building.rename(final)
    finally:
        shutil.rmtree(building, ignore_errors=True)
