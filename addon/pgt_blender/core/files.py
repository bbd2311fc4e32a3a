"""Output files that appear complete or not at all, and the checks of input files."""

import os
import stat
from contextlib import contextmanager
from pathlib import Path

from .errors import InputError


@contextmanager
def atomic_output(path, writer: str = ""):
    """A binary stream to a temporary file beside ``path``, renamed onto ``path`` when
    the block ends without error and removed otherwise. A failed write (disk full,
    permission) raises OSError naming ``path``, not the temporary file. ``writer`` names
    the temporary for processes that may write the same ``path`` at once (each its own)."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}{writer}.partial")
    try:
        with open(temporary, "wb") as stream:
            yield stream
        os.replace(temporary, path)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        if error.filename not in (None, str(temporary)):
            raise
        raise OSError(error.errno, error.strerror, str(path)) from error
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def read_float32_rows(path, columns: int = 1, what: str = "values"):
    """(N, columns) float32 rows of a raw little-endian float32 file (KITTI velodyne
    scans, ground-truth database .bin files); InputError naming ``path`` when it cannot
    be read or its size is not a whole number of rows (a cut or padded file)."""
    import numpy as np

    path = regular_file(path)
    try:
        data = np.fromfile(path, "<f4")
        size = path.stat().st_size
    except OSError as error:
        raise InputError(path, f"cannot read the file ({error.strerror or error})") from None
    if size % (4 * columns):
        raise InputError(path, f"{size} bytes are not whole rows of {columns} float32 {what}")
    unusable = int(np.count_nonzero(~np.isfinite(data)))
    if unusable:
        raise InputError(path, f"{unusable} of {data.size} float32 {what} are NaN or Inf")
    return data.reshape(-1, columns)


def regular_file(path) -> Path:
    """``path`` when it names a regular file (links followed); InputError for a missing
    path, a folder, or a pipe or device, which a read would wait on or never finish."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except OSError as error:
        raise InputError(path, f"cannot read the file ({error.strerror or error})") from None
    except ValueError:  # a NUL byte in the path
        raise InputError(path, "not a usable file name (it holds a NUL byte)") from None
    if stat.S_ISDIR(mode):
        raise InputError(path, "is a folder; expected a file")
    if not stat.S_ISREG(mode):
        raise InputError(path, "not a regular file (a pipe, socket or device); expected a file")
    return path
