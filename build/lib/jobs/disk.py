"""``is_disk_full(err)``: whether an error is the disk being full (the file system's ENOSPC or
EDQUOT, or SQLite's SQLITE_FULL), anywhere in its chain of causes. A full disk is the server's
state, not the job's fault: a job that meets it goes back to the queue with its upload
(``DiskFull``), and the API answers 507."""

from __future__ import annotations

import errno
import sqlite3

SQLITE_FULL = 13
# The job process's exit status when it stopped on a full disk (EX_TEMPFAIL: try again later).
EXIT_DISK_FULL = 75


class DiskFull(Exception):
    """A job stopped because the disk is full; its attempt ends without ending the job."""


def is_disk_full(err: BaseException | None) -> bool:
    seen = 0
    while err is not None and seen < 16:
        if isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if isinstance(err, sqlite3.OperationalError) and (
            getattr(err, "sqlite_errorcode", None) == SQLITE_FULL or "disk is full" in str(err)
        ):
            return True
        err, seen = err.__cause__ or err.__context__, seen + 1
    return False
