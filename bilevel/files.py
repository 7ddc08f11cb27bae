"""Whole-file writes that are never seen half-done: write a temporary file beside the target, fsync, os.replace.

A run killed mid-write leaves the previous file (or none) and at most a hidden temporary `.<name>.<tag><ext>`;
readers never meet a truncated table, report, figure or timings.json.
"""

from __future__ import annotations

import csv
import errno
import os
import uuid
from collections.abc import Iterable, Mapping
from contextlib import contextmanager
from typing import IO, Any, Iterator


@contextmanager
def atomic_path(path: str) -> Iterator[str]:
    """A temporary name beside `path` (same extension, so savefig and np.savez keep the format) to write to;
    on normal exit it is fsynced and renamed over `path`, on an exception removed. A `path` that exists and is no
    regular file (a device such as /dev/full, a pipe) is an OSError before anything is written: the rename would
    replace it."""
    if os.path.exists(path) and not os.path.isfile(path):  # a rename would replace a device (/dev/full) or a pipe
        raise OSError(errno.EINVAL, "not a regular file (a device, pipe or socket); give a file path", path)
    directory, name = os.path.split(os.path.abspath(path))
    ext = os.path.splitext(name)[1]
    tmp = os.path.join(directory, f".{name}.{os.getpid()}-{uuid.uuid4().hex[:8]}{ext}")
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    if hasattr(os, "O_DIRECTORY"):  # make the rename itself durable (POSIX)
        fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextmanager
def atomic_open(path: str, mode: str = "w", encoding: str | None = "utf-8", newline: str | None = None) -> Iterator[IO]:
    """open(path, mode) whose content replaces `path` only once the block finished (see atomic_path)."""
    with atomic_path(path) as tmp:
        with open(tmp, mode, encoding=None if "b" in mode else encoding, newline=newline) as fh:
            yield fh
            fh.flush()


def save_figure(fig: Any, out_dir: str, name: str) -> str:
    """Write a matplotlib figure as out_dir/name.png and .pdf (each atomically, tight bounding box), close it if
    pyplot manages it, and return "name.png" (what a report links)."""
    for ext in ("png", "pdf"):
        with atomic_path(os.path.join(out_dir, f"{name}.{ext}")) as tmp:
            fig.savefig(tmp, dpi=130, bbox_inches="tight")
    import matplotlib.pyplot as plt  # imported here: files.py is used where matplotlib is not

    plt.close(fig)
    return f"{name}.png"


def write_rows_csv(path: str, rows: Iterable[Mapping[str, Any]], fields: Iterable[str]) -> None:
    """Write `fields` of each row as CSV (a header line, then one line per row), atomically."""
    fields = list(fields)
    with atomic_open(path, newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        writer.writerows({k: r[k] for k in fields} for r in rows)
