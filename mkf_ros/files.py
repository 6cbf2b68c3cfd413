"""Files written whole or not at all: the one write-to-a-temporary-name-then-rename of the
package (results, reports, figures, parameter files), so that a reader, a killed run or a full
disk never leaves half a file under the final name. Bags are directories and have their own
(:class:`mkf_ros.bags.writer.BagWriter`)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

#: What the temporary names contain (``.NAME.PID.tmpSUFFIX`` beside the file): a folder's
#: leftovers of a killed run match ``.*.tmp*``.
TMP_MARK = ".tmp"


def temporary_name(path: Path) -> Path:
    """The temporary name of ``path`` for this process: hidden, beside it (the same file
    system, so the rename is atomic), with its suffix (which matplotlib and NumPy read)."""
    return path.with_name(f".{path.name}.{os.getpid()}{TMP_MARK}{path.suffix}")


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path to write ``path``'s content to; when the block ends without an
    exception the file is flushed to disk and renamed onto ``path`` (replacing it), otherwise
    removed.

    ::

        with atomic_path(out / "plot.png") as tmp:
            fig.savefig(tmp)
    """
    path = Path(path)
    tmp = temporary_name(path)
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` whole or not at all (:func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` whole or not at all (:func:`atomic_path`)."""
    write_bytes(path, text.encode())
