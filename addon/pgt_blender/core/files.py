"""Output files that appear complete or not at all, and the checks of input files."""

import hashlib
import os
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path

from .errors import InputError

NAME_MAX = 255  # bytes in a file name on Linux, macOS and Windows file systems


@contextmanager
def atomic_output(path, writer: str = ""):
    """A binary stream to a temporary file beside ``path`` (its missing folders made, and
    removed again on failure: folders_made), renamed onto ``path`` when the block ends
    without error and removed otherwise. A failed write (disk full, permission) raises
    OSError naming ``path``, not the temporary file. ``writer`` names the temporary for
    processes that may write the same ``path`` at once (each its own)."""
    path = Path(path)
    name = f".{path.name}{writer}.partial"
    if len(os.fsencode(name)) > NAME_MAX:  # a legal name of 247-255 bytes: a shorter temporary
        name = f".{hashlib.sha256(os.fsencode(path.name)).hexdigest()[:32]}{writer}.partial"
    temporary = path.with_name(name)
    with folders_made(path.parent):
        try:
            with open(temporary, "wb") as stream:
                yield stream
            os.replace(temporary, path)
        except OSError as error:
            _discard(temporary)
            if error.filename is not None and os.fspath(error.filename) != os.fspath(temporary):
                raise
            # numpy's tofile raises an OSError of no errno: its own text is the reason then
            raise OSError(error.errno, error.strerror or f"write failed ({error})", str(path)) from error
        except BaseException:
            _discard(temporary)
            raise


def _discard(path: Path) -> None:
    """Remove ``path`` if it is there; a folder that cannot hold it (a file in the
    way: NotADirectoryError) has nothing to remove either."""
    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass


@contextmanager
def folders_made(folder):
    """Make ``folder`` and its missing parents; when the block fails, remove those it
    made that are empty again (a failed step leaves no empty output folder)."""
    folder = Path(folder)
    made = missing_folders(folder)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        yield folder
    except BaseException:
        remove_empty(made)
        raise


def missing_folders(folder: Path) -> list:
    """``folder`` and its parents that do not exist yet, innermost first."""
    return [path for path in (folder, *folder.parents) if not path.exists()]


def remove_empty(folders: list) -> None:
    """Remove those of ``folders`` (innermost first) that are empty folders."""
    for path in folders:
        if path.is_dir() and not any(path.iterdir()):
            path.rmdir()


def output_path(path, folder: bool = False, suffixes: tuple = ()) -> Path:
    """``path`` when an output file (``folder``: an output folder) can be made there;
    InputError naming it when something is in the way: a folder where the file goes, a
    file where the folder goes, a file among its parents, a file name not ending in one
    of ``suffixes`` (when given), or a nearest existing folder that takes no new file
    (read-only, /proc; probed with a temporary file, removed at once). Checked before the
    work, so that a long run does not fail at its end."""
    path = Path(path)
    if path.exists() and path.is_dir() != folder:
        raise InputError(path, "is a file, not an output folder" if folder else "is a folder; expected a file name")
    if suffixes and path.suffix not in suffixes:
        raise InputError(path, f"expected a file name ending in {' or '.join(suffixes)}")
    start = path.absolute() if folder else path.absolute().parent
    nearest = next(parent for parent in (start, *start.parents) if parent.exists())
    if not nearest.is_dir():
        raise InputError(path, f"cannot be made: it lies under the file {nearest}")
    try:
        with tempfile.TemporaryFile(dir=nearest):
            pass
    except OSError as error:
        raise InputError(path, f"cannot be written: {nearest} takes no new file ({error.strerror})") from None
    return path


def read_toml(path: Path) -> dict:
    """The table of the TOML file ``path`` (its caller checked it: regular_file);
    InputError naming it when it cannot be read or parsed, or nests too deeply for the
    parser."""
    import tomllib

    try:
        return tomllib.loads(path.read_text())
    except (OSError, ValueError) as error:  # ValueError: bad TOML or UTF-8, an integer beyond int()'s digits
        raise InputError(path, f"not a readable TOML file: {error}") from None
    except RecursionError:
        raise InputError(path, "not a readable TOML file: nested too deeply") from None


def apart_from_inputs(out, inputs) -> None:
    """InputError naming the output ``out`` (a file, or a folder the command writes into)
    when it is one of ``inputs`` (paths; None or "" skipped) or, as a folder, directly holds
    an input file: writing it would destroy what the command reads. Inputs deeper down
    (a KITTI folder's velodyne/ under ``--out .``) are left alone. No output (None):
    nothing to check."""
    given = None if out is None else held_input(out, inputs)
    if given is not None:
        raise InputError(out, f"is or holds the input {given}; write the output elsewhere")


def held_input(out, inputs, anywhere: bool = False):
    """The first of ``inputs`` (paths; None or "", a setting left empty, skipped: "" would
    resolve to the working folder) that is ``out`` or lies in it as a folder: as a file
    directly in it, or with ``anywhere`` at any depth; None if none."""
    target = Path(out).resolve()
    for given in inputs:
        if given is None or given == "":
            continue
        source = Path(given).resolve()
        if source == target or (source.parent == target and source.is_file()) or (
                anywhere and source.is_relative_to(target)):
            return given
    return None


def npy_header(stream, path, where: str = "") -> tuple:
    """(shape, dtype) of the .npy array at ``stream``'s position, read without the
    array (numpy allocates what a header declares before reading); InputError naming
    ``path`` (and ``where`` in it) for a header numpy cannot read."""
    import numpy as np

    readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    try:
        version = np.lib.format.read_magic(stream)
        if version not in readers:
            raise ValueError(f".npy format version {version} is not read")
        shape, _, dtype = readers[version](stream)
    except (ValueError, EOFError) as error:
        raise InputError(path, f"{where}not a readable .npy header ({error})") from None
    return shape, dtype


def read_float32_rows(path, columns: int = 1, what: str = "values", rows: int | None = None):
    """(N, columns) float32 rows of a raw little-endian float32 file (KITTI velodyne
    scans, ground-truth database .bin files); InputError naming ``path`` when it cannot
    be read (also: larger than the memory), its size is not a whole number of rows (a
    cut or padded file) or not the ``rows`` its info declares. Sizes are checked before
    the read: a file of gigabytes where a few rows are due stays unread."""
    import numpy as np

    path = regular_file(path)
    try:
        size = path.stat().st_size
        if size % (4 * columns):
            raise InputError(path, f"{size} bytes are not whole rows of {columns} float32 {what}")
        if rows is not None and size // (4 * columns) != rows:
            raise InputError(path, f"{size // (4 * columns)} rows of {columns} float32 {what}, but its info "
                                   f"declares {rows}")
        data = np.fromfile(path, "<f4")
    except OSError as error:
        raise InputError(path, f"cannot read the file ({error.strerror or error})") from None
    except MemoryError:  # a file larger than the memory: named, not just "out of memory"
        raise InputError(path, f"too large to read ({size / 2**30:.1f} GiB)") from None
    unusable = int(np.count_nonzero(~np.isfinite(data)))
    if unusable:
        raise InputError(path, f"{unusable} of {data.size} float32 {what} are NaN or Inf")
    return data.reshape(-1, columns)


# bytes: far above any config, label, calibration, sidecar, map or camera list; a text
# input beyond it is the wrong file, which parsing would hold in memory many times over
TEXT_LIMIT = 256 * 2**20


def no_dead_link(path) -> Path:
    """``path``; InputError naming it when it is a link that leads nowhere (its target
    missing, or a loop of links): it reads as no file at all, which a message must not
    claim."""
    path = Path(path)
    if path.is_symlink() and not path.exists():
        raise InputError(path, "a link that leads nowhere (its target is missing, or the links loop)")
    return path


def listed(folder, pattern: str) -> list:
    """The paths in the folder ``folder`` matching ``pattern`` (Path.glob), sorted;
    InputError naming the folder when it cannot be read (glob passes over it in silence,
    as if empty) or a match that is a link leading nowhere (no_dead_link)."""
    folder = Path(folder)
    try:
        os.scandir(folder).close()
    except OSError as error:
        raise InputError(folder, f"cannot be read ({error.strerror or error})") from None
    return [no_dead_link(path) for path in sorted(folder.glob(pattern))]


def regular_file(path, limit: int | None = None) -> Path:
    """``path`` when it names a regular file (links followed) of at most ``limit``
    bytes, when given (TEXT_LIMIT for text inputs); InputError for a missing path, a
    folder, a pipe or device, which a read would wait on or never finish, or a larger
    file."""
    path = Path(path)
    try:
        status = path.stat()
    except OSError as error:
        no_dead_link(path)  # a dead link in its own words, not "No such file"
        raise InputError(path, f"cannot read the file ({error.strerror or error})") from None
    except ValueError:  # a NUL byte in the path
        raise InputError(path, "not a usable file name (it holds a NUL byte)") from None
    if stat.S_ISDIR(status.st_mode):
        raise InputError(path, "is a folder; expected a file")
    if not stat.S_ISREG(status.st_mode):
        raise InputError(path, "not a regular file (a pipe, socket or device); expected a file")
    if limit is not None and status.st_size > limit:
        raise InputError(path, f"too large for what is read from it ({status.st_size:,} bytes, more than "
                               f"{limit / 2**20:,.0f} MB): the wrong file?")
    return path
