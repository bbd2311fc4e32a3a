"""Where a bank's chunks run: this process, a local process pool, or a Ray cluster.
Each runs ``write(job, cache, chunk_id, entries)`` (export.write_chunk) for the pending
chunks and yields what it returns (export.ChunkDone) as each finishes; a worker holds one job and one
TargetCache (one ray target per object, or per splat variant, reused across its chunks)."""

import ctypes
import os
import sys
from pathlib import Path

import numpy as np

from ..errors import InputError
from .entries import TargetCache

# One job per worker process, set by the pool's initializer (or before a fork).
_job = None
_write = None
_cache: TargetCache | None = None
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's malloc.h (mallopt)


def start_worker(job, write) -> None:
    global _job, _write, _cache
    if "bpy" not in sys.modules:
        # A spawned worker inherits the parent's sys.path, to which the bpy module added
        # its scripts folders; their "bpy" package would shadow the module itself.
        sys.path[:] = [path for path in sys.path if Path(path).parent.name != "scripts"]
    _job, _write, _cache = job, write, TargetCache(job.objects, job.config)
    keep_freed_memory()


def keep_freed_memory() -> None:
    """Have glibc's malloc keep freed memory for reuse rather than hand it back to the
    system: a chunk's numpy temporaries (up to tens of MB each) otherwise come back as
    fresh pages every chunk, and faulting them in took about 6 % of a worker's CPU
    (bench_bank). For processes that only export (pool and Ray workers, the command
    line): their memory then stays at its peak. Elsewhere than Linux, nothing."""
    if sys.platform != "linux":
        return
    mallopt = ctypes.CDLL(None).mallopt
    mallopt(M_MMAP_THRESHOLD, 64 * 2**20)  # blocks below it come from the reusable heap
    mallopt(M_TRIM_THRESHOLD, 512 * 2**20)  # free heap kept up to this


def run_chunk(chunk_id: int, entries: np.ndarray):
    """Export one chunk in this worker (``start_worker`` first); returns what ``write`` does."""
    return _write(_job, _cache, chunk_id, entries)


def run_local(job, chunks: list, pending: list, workers: int, write):
    """Yield each pending chunk's ChunkDone as it finishes, on ``workers`` processes
    (1: in this process). Linux forks (the BVH library is already loaded), except for a
    learned intensity: PyTorch's thread pool does not survive a fork, so those workers,
    like every worker elsewhere, are spawned with the job."""
    if workers <= 1 or len(pending) <= 1:
        if "bpy" not in sys.modules:  # Blender's own process keeps its allocator's defaults
            keep_freed_memory()
        cache = TargetCache(job.objects, job.config)
        for chunk_id in pending:
            yield write(job, cache, chunk_id, chunks[chunk_id])
        return
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    forks = sys.platform == "linux" and not job.config.intensity_checkpoint
    context = multiprocessing.get_context("fork" if forks else "spawn")
    with ProcessPoolExecutor(workers, context, initializer=start_worker, initargs=(job, write)) as pool:
        queue = list(pending)
        running = set()
        while queue or running:
            # A bounded queue: at most two chunks per worker wait, so memory stays flat.
            while queue and len(running) < 2 * workers:
                chunk_id = queue.pop(0)
                running.add(pool.submit(run_chunk, chunk_id, chunks[chunk_id]))
            done, running = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                yield future.result()


def check_ray_address(address: str | None, timeout: float = 5.0) -> None:
    """InputError unless a Ray head answers at ``address`` ("HOST:PORT" or
    "ray://HOST:PORT"; None and "auto" are left to Ray): ray.init retries an
    unreachable address without end. Checked before the export writes anything."""
    import socket

    if address in (None, "auto", "local"):
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(address, "not a Ray cluster address (HOST:PORT or ray://HOST:PORT)")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as error:
        raise InputError(address, f"no Ray cluster answers there ({error.strerror or error})") from None


def run_ray(job, chunks: list, pending: list, address: str | None, write):
    """The same chunks as tasks on a Ray cluster (``address`` None: a local one). Every
    node must see ``job.out`` (a shared file system) and have pgt_blender's Python."""
    import ray

    ray.init(address=address, ignore_reinit_error=True, log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join(p for p in _python_path() if p)}})
    try:
        job_ref = ray.put(job)
        remote = ray.remote(_ray_chunk)
        running = [remote.remote(job_ref, write, chunk_id, chunks[chunk_id]) for chunk_id in pending]
        while running:
            done, running = ray.wait(running, num_returns=1)
            yield ray.get(done[0])
    finally:
        ray.shutdown()


def _python_path() -> list:
    """This process's import path for pgt_blender, so Ray workers find the same code."""
    package_parent = str(Path(__file__).resolve().parents[3])
    return [package_parent, os.environ.get("PYTHONPATH", "")]


def _ray_chunk(job, write, chunk_id: int, entries: np.ndarray):
    """One chunk as a Ray task: a worker process starts the job on its first task."""
    if _job is None or _job.out != job.out:
        start_worker(job, write)
    return run_chunk(chunk_id, entries)
