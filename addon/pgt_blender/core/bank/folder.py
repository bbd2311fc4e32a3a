"""The bank folder's life cycle (export.py fills it)::

    OUT/manifest.json                           config, objects, versions, counts, sha256 per file
    OUT/<format>/<dataset>_dbinfos_pgt.pkl      the info pickle (formats.py)
    OUT/<format>/pgt_gt_database/<object>_<class>_<index>.bin
    OUT/.work/identity.json                     what this bank is made of (checked on --resume)
    OUT/.work/chunks/<chunk>.json               one chunk's infos, file checksums and statistics (records.py)

A chunk is done exactly when its record exists (its entry files are written first, then
the record, atomically; a chunk cut short is redone whole): a folder is made ready once
(``prepare_folder``), its pending chunks are those without a whole record, shards'
records are copied in, and every reader of ``.work`` goes through here with one error
policy (InputError naming the file). An export holds its folder (``exporting``) so that
a second one into the same folder is refused rather than mixed in.
"""

import hashlib
import json
import os
import shutil
import socket
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import TEXT_LIMIT, atomic_output, held_input, missing_folders, output_path, regular_file, remove_empty
from .records import read_record

WORK = ".work"
MANIFEST = "manifest.json"
INTENSITY_BINS = 32  # the report's per-class intensity histograms, over the dataset's range
STATS_DTYPE = np.dtype([("object", "i4"), ("index", "i4"), ("x", "f4"), ("y", "f4"), ("heading", "f4"),
                        ("points", "i4"), ("kept", "?")])
BUSY = ("another export is using this folder right now (exporting, resuming or assembling a bank there); wait "
        "for it to end or choose another output folder")
SHARD_BUSY = "a shard is still exporting there (or another assembly copies from it); wait for it to end"


@contextmanager
def exporting(out: Path, shared: bool = False):
    """Hold the bank folder ``out`` for the block (an export, a resume, an overwrite or an
    assembly): made if missing (and removed again, with the parents it needed, when the
    block fails and leaves it empty), and locked with an advisory ``flock`` on the folder
    itself, so that another process's export into it is refused with InputError instead
    of mixing its chunks in. Shards of one array job (``shared``) hold it together, but
    not beside anything else. A refused export removes nothing (the folder is the other
    one's); a failed one removes what it made while it still holds the folder. Where the
    file system has no such lock (Windows, some network shares) the block runs unlocked."""
    output_path(out, folder=True)
    made = missing_folders(out)
    with _holding(out, shared, BUSY):
        try:
            yield
        except BaseException:
            remove_empty(made)
            raise


@contextmanager
def _holding(folder: Path, shared: bool, busy: str):
    """Hold ``folder`` (made if missing) locked for the block; InputError ``busy`` when
    another process holds it."""
    descriptor = _lock(folder, shared, busy)
    try:
        yield
    finally:
        if descriptor is not None:
            _HELD.discard(descriptor)
            os.close(descriptor)


# Descriptors holding a folder's lock in this process. A process forked meanwhile (a
# pool worker) closes its copies: a flock lasts while any copy is open, and a worker
# left running after its export was killed would hold the folder for good.
_HELD = set()


def _close_held_copies() -> None:
    for descriptor in _HELD:
        os.close(descriptor)
    _HELD.clear()


if hasattr(os, "register_at_fork"):  # not on Windows, which has no flock either
    os.register_at_fork(after_in_child=_close_held_copies)


def _lock(out: Path, shared: bool, busy: str) -> int | None:
    """Make the folder ``out`` and return an open descriptor of it holding its flock
    (closing it releases the lock), or None where locks are not to be had; InputError
    ``busy`` when another holds it."""
    out.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # Windows
        return None
    descriptor = os.open(out, os.O_RDONLY)
    try:
        fcntl.flock(descriptor, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        # the folder removed (a failed export's cleanup) and made again since it was opened: not the one locked
        held = os.path.samestat(os.fstat(descriptor), os.stat(out))
    except (BlockingIOError, FileNotFoundError):  # held by another, or removed since it was opened
        held = False
    except OSError:  # no locks on this file system: unlocked, as on Windows
        os.close(descriptor)
        return None
    if not held:
        os.close(descriptor)
        raise InputError(out, busy)
    _HELD.add(descriptor)
    return descriptor


def prepare_folder(out: Path, ident: dict, resume: bool, overwrite: bool, shared: bool = False,
                   inputs=()) -> None:
    """Make ``out`` ready: new or empty; with ``overwrite`` an earlier bank there is
    removed, unless one of ``inputs`` (paths, None or "" skipped: the .blend, config, sensor,
    checkpoint, real database) lies in it; with ``resume`` (or ``shared``, for shards) an
    unfinished bank of the same identity is continued. Anything else is refused with
    InputError."""
    marker = out / WORK / "identity.json"
    output_path(out, folder=True)
    if shared and not marker.is_file() and _unstarted(out):
        _start_shared(out, ident)
        return
    if _cut_short(out):
        shutil.rmtree(out / WORK)
    if out.is_dir() and any(out.iterdir()):
        is_bank = marker.is_file() or (out / MANIFEST).is_file()
        if overwrite:
            if not is_bank:
                raise InputError(out, "is not empty and holds no bank: refusing to delete it; choose another --out")
            inside = held_input(out, inputs, anywhere=True)
            if inside is not None:
                raise InputError(out, f"holds the input {inside}, which overwriting the bank would delete; "
                                      "move it or write the bank elsewhere")
            for child in out.iterdir():  # a link is removed, not what it points to (rmtree refuses links)
                shutil.rmtree(child) if child.is_dir() and not child.is_symlink() else child.unlink()
        elif resume or shared:
            if not marker.is_file():
                raise InputError(out, "holds no unfinished bank to resume (no .work/identity.json)")
            if read_identity(out) != ident:
                raise InputError(out, "holds a bank of other objects or settings; use --overwrite or another --out")
            return
        else:
            raise InputError(out, "is not empty: resume the bank there or overwrite it (--resume / --overwrite; the "
                                  "Bank panel's 'If it exists')")
    (out / WORK / "chunks").mkdir(parents=True, exist_ok=True)
    with atomic_output(marker) as stream:
        stream.write(json.dumps(ident, indent=1).encode())


def _unstarted(out: Path) -> bool:
    """True for a folder that is missing, empty, or holds only a .work with no chunk
    record yet: a bank not started, or being started by another shard right now."""
    return not out.is_dir() or ({child.name for child in out.iterdir()} <= {WORK}
                                and not any((out / WORK / "chunks").glob("*.json")))


def _start_shared(out: Path, ident: dict) -> None:
    """Start a bank that shards may start together (an array job's tasks): each makes the
    folders and writes the same identity through a temporary of its own, and none
    removes what another is making; a shard of other settings that wrote last is named."""
    (out / WORK / "chunks").mkdir(parents=True, exist_ok=True)
    with atomic_output(out / WORK / "identity.json", f".{socket.gethostname()}-{os.getpid()}") as stream:
        stream.write(json.dumps(ident, indent=1).encode())
    if read_identity(out) != ident:
        raise InputError(out, "holds a bank of other objects or settings; use --overwrite or another --out")


def _cut_short(out: Path) -> bool:
    """True for a folder holding only the empty .work/chunks an export makes before its
    identity: a start cut short (a full disk), with nothing in it to keep."""
    def names(folder: Path) -> list:
        return sorted(child.name for child in folder.iterdir()) if folder.is_dir() else []

    return names(out) == [WORK] and names(out / WORK) == ["chunks"] and not names(out / WORK / "chunks")


def read_identity(out: Path) -> dict:
    """OUT/.work/identity.json; InputError naming the file when it is missing or damaged."""
    path = out / WORK / "identity.json"
    if not path.is_file():
        raise InputError(out, f"is not a bank folder: no {WORK}/identity.json")
    ident = _json_file(path, "; --overwrite starts the bank anew")
    if not (isinstance(ident, dict) and {"config", "objects", "class_names", "chunks"} <= ident.keys()):
        raise InputError(path, "not a bank identity (config, objects, class_names, chunks); --overwrite starts "
                               "the bank anew")
    return ident


def read_manifest(out: Path) -> dict:
    """OUT/manifest.json of a finished bank; InputError naming the folder when there is
    none (no such folder, not a bank, or an export not assembled yet) or naming the file when damaged:
    not JSON, a key missing, a config that fails a config file's checks, or not one info
    pickle per format."""
    from .config import config_from_dict

    path = Path(out) / MANIFEST
    if not Path(out).is_dir():
        raise InputError(out, "no such folder" if not Path(out).exists() else "is not a folder (a bank is a folder)")
    if not path.is_file():
        raise InputError(out, f"is not a finished bank: no {MANIFEST} (an export still running or stopped is "
                              "finished by resuming it)")
    manifest = _manifest_json(path)
    if not {"config", "info_pickles", "entries"} <= manifest.keys():
        raise InputError(path, "not a bank manifest (config, info_pickles, entries)")
    formats = config_from_dict(manifest["config"], path).formats
    pickles = manifest["info_pickles"]
    if not (isinstance(pickles, dict) and set(pickles) == set(formats)
            and all(isinstance(name, str) and name and "\0" not in name for name in pickles.values())):
        raise InputError(path, f"info_pickles must name one pickle file per format ({', '.join(formats)})")
    _data_root(path, manifest.get("data_root"))
    return manifest


def chunk_record_path(out: Path, chunk_id: int) -> Path:
    return out / WORK / "chunks" / f"{chunk_id:06d}.json"


def chunk_record(out: Path, chunk_id: int, path: Path | None = None) -> dict | None:
    """The record of chunk ``chunk_id`` (read from ``path``, default its place in OUT),
    or None when it is missing or damaged. Checked field by field."""
    path = chunk_record_path(out, chunk_id) if path is None else path
    if not path.is_file():
        return None
    try:
        record = read_record(path)
    except (OSError, ValueError, TypeError, KeyError, RecursionError):  # what damaged JSON or array fields raise
        return None
    fields = {"chunk": int, "infos": dict, "files": dict, "stats": np.ndarray, "intensity": dict}
    whole = isinstance(record, dict) and all(isinstance(record.get(key), kind) for key, kind in fields.items()) \
        and record["chunk"] == chunk_id and record["stats"].dtype == STATS_DTYPE \
        and all(isinstance(infos, list) and all(isinstance(info, dict) for info in infos)
                for infos in record["infos"].values()) \
        and all(_in_bank(name) and isinstance(digest, str) for name, digest in record["files"].items())
    return record if whole else None


def _in_bank(name) -> bool:
    """Whether a record's file ``name`` is a path inside the bank (relative, no ``..``):
    a damaged or crafted record must not make a copy or a check reach outside it."""
    return isinstance(name, str) and bool(name) and "\0" not in name and not os.path.isabs(name) \
        and ".." not in Path(name).parts


def done_chunk(out: Path, chunk_id: int, path: Path | None = None) -> dict | None:
    """chunk_record when every entry file it lists is in ``out`` too, else None: a chunk
    with a damaged record or a lost file (deleted after the export, a shard copied in
    part) is not done, and is redone."""
    record = chunk_record(out, chunk_id, path)
    return record if record is not None and all((out / name).is_file() for name in record["files"]) else None


def pending_chunks(out: Path, chunk_count: int, shard=(0, 1)) -> list:
    """The chunk ids of this shard (id % count == index) without a whole record."""
    index, count = shard
    return [i for i in range(index, chunk_count, count) if done_chunk(out, i) is None]


def copy_shard(source: Path, out: Path) -> int:
    """Copy a shard folder's done chunks (done_chunk: the records and their database
    files) into ``out`` (same identity required); returns the records copied. The
    others are left: their chunks stay to do. A shard folder an export still holds is
    refused (InputError), not copied in part."""
    if Path(source).resolve() == Path(out).resolve():
        raise InputError(source, "is the bank being assembled (--out); --from takes the shards' folders")
    if read_identity(source) != read_identity(out):
        raise InputError(source, "is not a shard of this bank (its .work/identity.json differs)")
    with _holding(source, False, SHARD_BUSY):
        return _copy_done_chunks(source, out)


def _copy_done_chunks(source: Path, out: Path) -> int:
    copied = 0
    for record_path in sorted((source / WORK / "chunks").glob("*.json")):
        record = done_chunk(source, int(record_path.stem), record_path) if record_path.stem.isdigit() else None
        if record is None:
            continue  # damaged or a file lost: the chunk stays to do
        for relative in record["files"]:
            target = out / relative
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source / relative, target)
        shutil.copyfile(record_path, out / WORK / "chunks" / record_path.name)  # last: the chunk counts once here
        copied += 1
    return copied


def info_path_root(info_pickle: Path) -> Path:
    """The folder a bank pickle's info paths are relative to: the data root its
    manifest records (OUT/manifest.json beside OUT/<format>/), else the pickle's folder
    (no manifest there: any other database). InputError naming the manifest when it
    cannot be read or its data root is no folder (the bank moved away from it)."""
    manifest = Path(info_pickle).parent.parent / MANIFEST
    if not manifest.is_file():
        return Path(info_pickle).parent
    data_root = _manifest_json(manifest).get("data_root")
    if _data_root(manifest, data_root) is None:
        return Path(info_pickle).parent
    root = manifest.parent / data_root
    if not root.is_dir():
        raise InputError(manifest, f"data_root '{data_root}' is no folder from here ({root}): move the bank back "
                                   f"or re-target it with export_bank.py --assemble --data-root")
    return root


def _manifest_json(path: Path) -> dict:
    """The JSON object of the bank manifest ``path`` (an existing file); InputError
    naming it when it is no regular file within TEXT_LIMIT, damaged, or no object."""
    manifest = _json_file(regular_file(path, TEXT_LIMIT))
    if not isinstance(manifest, dict):
        raise InputError(path, "not a bank manifest (config, info_pickles, entries)")
    return manifest


def _json_file(path: Path, fix: str = ""):
    """The JSON value of the bank's own file ``path``; InputError "damaged (...)" naming
    it, then ``fix``, when it cannot be read or parsed."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as error:  # ValueError: bad JSON or UTF-8, a huge integer
        raise InputError(path, f"damaged ({type(error).__name__}: {error}){fix}") from None


def _data_root(manifest: Path, value):
    """A manifest's ``data_root`` (relative to OUT): None or a folder path; InputError
    naming ``manifest`` otherwise."""
    if value is not None and not (isinstance(value, str) and value and "\0" not in value):
        raise InputError(manifest, "data_root must be a folder path or null")
    return value


def write_entry_file(path: Path, data) -> str:
    """Write one entry's file (its folder exists) in place and return its sha256: not
    through a temporary file, since the chunk record that lists it is written after it
    (atomically) and a chunk without a record is redone whole; a write that fails
    removes the file and names it. ``data``: bytes or a C-contiguous array. Four
    system calls (open, write, fadvise, close): a bank makes millions of these files;
    the fadvise starts the file's write-back now, so that ``drop_cached`` can free its
    pages once the chunk is written."""
    view = whole = memoryview(data).cast("B")
    try:
        descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_BINARY", 0), 0o666)
        try:
            while view:
                view = view[os.write(descriptor, view):]
            _advise_dont_need(descriptor)
        finally:
            os.close(descriptor)
    except BaseException as error:
        path.unlink(missing_ok=True)
        if isinstance(error, OSError) and error.filename is None:
            raise OSError(error.errno, error.strerror, str(path)) from error
        raise
    return hashlib.sha256(whole).hexdigest()


def drop_cached(paths) -> None:
    """Free the page-cache pages of written files whose write-back has ended (others
    stay cached; nothing changes on disk). A bank is written once and read later by a
    trainer, so caching it would only evict the machine's useful cache, and every new
    cache page costs system time to touch (8-10 us per 4 kB page on a VM whose host
    backs memory on first use: bench/bank_embree.md); dropped pages are reused hot. A
    no-op where the OS has no posix_fadvise (Windows, macOS)."""
    if not hasattr(os, "posix_fadvise"):
        return
    for path in paths:
        try:
            descriptor = os.open(path, os.O_RDONLY)
        except OSError:
            continue  # a file removed meanwhile has no pages to drop
        try:
            _advise_dont_need(descriptor)
        finally:
            os.close(descriptor)


def _advise_dont_need(descriptor: int) -> None:
    """POSIX_FADV_DONTNEED on the whole file: Linux starts the write-back of its dirty
    pages and frees its clean ones. Advice only: where a file system refuses it, the
    file just stays cached."""
    if hasattr(os, "posix_fadvise"):
        try:
            os.posix_fadvise(descriptor, 0, 0, os.POSIX_FADV_DONTNEED)
        except OSError:
            pass


def write_file(path: Path, data: bytes) -> str:
    """Write ``data`` atomically (parents made) and return its sha256."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as stream:
        stream.write(data)
    return hashlib.sha256(data).hexdigest()
