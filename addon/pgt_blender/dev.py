"""Helpers of the repository's scripts and tests, not shipped in the extension
(build_extension.py leaves this file out): where the third-party test data lies, how
benchmarks state their machine and write <out>.json and <out>.png, and a Ray cluster of
several nodes started on this machine (local_ray_cluster).

The shared data (real scans, meshes, COLMAP, splats, calibration tables, the detector
consumers) is ``$PGT_SHARED_DATA`` when set, else ``../shared/data`` beside the
repository: the one setting every script default and test reads.
"""

import json
import os
import platform
import sys
from contextlib import contextmanager
from pathlib import Path

from .cli import markdown_table  # noqa: F401  (the benchmarks' tables: one home, in cli)

REPOSITORY = Path(__file__).resolve().parents[2]
SHARED_DATA = Path(os.environ.get("PGT_SHARED_DATA") or REPOSITORY.parent / "shared" / "data")
CHRONO_VEHICLES = SHARED_DATA / "chrono_vehicles" / "data" / "vehicle"


def shown_path(path) -> str:
    """``path`` as reports print it, so a report names no one machine's folders: relative
    to the repository when it lies inside it or beside it (``../shared/...``), else
    absolute."""
    path = Path(path).resolve()
    if path.is_relative_to(REPOSITORY):
        return path.relative_to(REPOSITORY).as_posix()
    if path.is_relative_to(REPOSITORY.parent):
        return f"../{path.relative_to(REPOSITORY.parent).as_posix()}"
    return str(path)


def machine(**details) -> dict:
    """The benchmark machine: CPU model, core count, Python version, then ``details``
    (library versions, settings)."""
    return {"cpu": _cpu_name(), "cores": os.cpu_count(), "python": platform.python_version(), **details}


def _cpu_name() -> str:
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def write_results(out: Path, results: dict, draw) -> None:
    """Write ``results`` to <out>.json and the figure ``draw(pyplot)`` returns to
    <out>.png (Agg backend: no screen needed), then say where they are."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(results, indent=2))
    figure = draw(plt)
    figure.tight_layout()
    figure.savefig(out.with_suffix(".png"), dpi=100)
    print(f"\nwrote {out.with_suffix('.json')} and {out.with_suffix('.png')}")


def write_report(out: Path, title: str, script: str, machine: dict, inputs: dict, body: str, results: dict,
                 draw) -> None:
    """A benchmark's whole output: <out>.md (markdown_report of ``title`` ... ``body``),
    then <out>.json and <out>.png (write_results of ``results`` and ``draw``)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(markdown_report(title, script, machine, inputs, body))
    write_results(out, results, draw)


def load_average() -> list:
    """The 1, 5 and 15 minute load averages: other work on the machine inflates timings."""
    return [round(value, 2) for value in os.getloadavg()]


def markdown_report(title: str, script: str, machine: dict, inputs: dict, body: str) -> str:
    """A benchmark's <out>.md: ``title``, the script that wrote it, the machine and its
    versions, ``inputs`` (key -> value; a dict or list value becomes a bullet list), then
    ``body`` (its tables)."""
    lines = [f"# {title}", "", f"Written by `headless_scripts/{script}` (its docstring describes the method).", "",
             "**machine and versions**: " + ", ".join(f"{key} {value}" for key, value in machine.items()), ""]
    for key, value in inputs.items():
        if isinstance(value, dict):
            lines += [f"**{key}**:", "", *(f"- {name}: {item}" for name, item in value.items()), ""]
        elif isinstance(value, list) and value and isinstance(value[0], str):
            lines += [f"**{key}**:", "", *(f"- {item}" for item in value), ""]
        else:
            lines += [f"**{key}**: {value}", ""]
    return "\n".join(lines) + "\n" + body.rstrip() + "\n"


# The quality score's ranking check (test_quality.py, bench_quality.py): KITTI classes
# the shared scans label, each from a real mesh (Chrono) or the built-in sample.
RANKING_OBJECTS = (("car", CHRONO_VEHICLES / "sedan" / "sedan_chassis_vis.obj"),
                   ("truck", CHRONO_VEHICLES / "truck" / "truck_chassis.obj"),
                   ("cyclist", None))


def ranking_objects(folder, dataset: str = "kitti") -> list:
    """BankObjects of RANKING_OBJECTS, prepared into ``folder`` (z up, the mesh's own
    heading, sized to the dataset's class mean)."""
    from .core.authoring.prepare import prepare, write_prepared
    from .core.bank.inputs import checked_objects, prepared_objects
    from .core.importing import load_reconstruction
    from .core.samples import write_sample

    folder = Path(folder)
    for class_name, mesh in RANKING_OBJECTS:
        if mesh is None:
            mesh = write_sample(folder / "sample_bicycle", "bicycle", seed=0, points=3000)["reconstruction.ply"]
            authored = prepare(load_reconstruction(mesh), class_name, dataset, up="pca", heading_method="baseline")
        else:
            authored = prepare(load_reconstruction(mesh), class_name, dataset, up="+z", heading_method="none")
        write_prepared(authored, class_name, dataset, folder / "prepared")
    found, incomplete = prepared_objects(folder / "prepared")
    return checked_objects(found, incomplete, False, folder / "prepared")


# How the tests and bench_placement judge whether a box stands on a scan's ground.
FOOTPRINT_RETURNS = 20  # returns under a footprint that make a judgement


def scan_ground_gap(points, box):
    """(gap, how): box bottom minus the scan's own ground at the box, m, for (N, >= 3)
    scan points (before anything was placed) and a (>= 7,) centre box. The ground is the
    median height of the lowest returns under the footprint (within 0.2 m of their 5th
    percentile; "footprint", with FOOTPRINT_RETURNS or more), else a plane fitted to the
    returns 0.3-4 m around it (bank.ground.fit_ground, "ring", with MIN_GROUND_POINTS or
    more), else (None, "none")."""
    import numpy as np

    from .core.bank.ground import MIN_GROUND_POINTS, fit_ground
    from .core.boxes import box_frame

    xyz = np.asarray(points, np.float64)[:, :3]
    box = np.asarray(box, np.float64)
    local = box_frame(xyz, box[:3], box[6])
    under = xyz[(np.abs(local[:, :2]) <= box[3:5] / 2).all(axis=1), 2]
    bottom = box[2] - box[5] / 2
    if len(under) >= FOOTPRINT_RETURNS:
        lowest = under[under <= np.percentile(under, 5) + 0.2]
        return float(bottom - np.median(lowest)), "footprint"
    fit = fit_ground(xyz, box[:3], box[3:6], box[6])
    if fit["points"] >= MIN_GROUND_POINTS:
        return fit["bottom_gap"], "ring"
    return None, "none"



# A Ray cluster of several nodes on this machine (test_bank_cluster.py, bench_cluster.py).
RAY_NODE_PORTS = ("--node-manager-port", "--object-manager-port", "--dashboard-agent-listen-port",
                  "--dashboard-agent-grpc-port", "--runtime-env-agent-port", "--metrics-export-port")
RAY_STOP_GRACE_S = 10.0


@contextmanager
def local_ray_cluster(node_cpus: tuple, object_store_bytes: int = 2**28):
    """A Ray cluster of ``len(node_cpus)`` nodes on this machine, started as a user starts
    one across machines: ``ray start --head``, then ``ray start --address`` for each other
    node, each node its own processes with ``node_cpus[i]`` CPUs, its own --temp-dir and
    free ports. Token authentication is on (RAY_AUTH_MODE=token on every node and driver,
    as Ray requires) with a fresh token in a file of the cluster's own folder
    (RAY_AUTH_TOKEN_PATH): ~/.ray is left alone. Yields (head address "ip:port", the
    environment a driver needs: this one plus the token settings, the node folders by
    node index). The folder is a short one in the system temp dir: Ray's Unix sockets
    live under --temp-dir and a socket path may not exceed 107 bytes.

    On exit, failure included, every process of these nodes and none other stops: each
    ``ray start`` runs in a session of its own, which its daemons and their workers keep;
    they get SIGTERM, then SIGKILL after RAY_STOP_GRACE_S (``ray stop`` would stop every
    Ray on the machine). Linux only (the sessions are read from /proc)."""
    import secrets
    import shutil
    import subprocess
    import tempfile

    ray = shutil.which("ray", path=str(Path(sys.executable).parent)) or shutil.which("ray")
    folder = Path(tempfile.mkdtemp(prefix="pgt-ray-"))
    sessions = []
    try:
        token = folder / "auth_token"
        token.touch(mode=0o600)
        token.write_text(secrets.token_hex(32))
        env = {key: value for key, value in os.environ.items() if key not in ("RAY_ADDRESS", "RAY_AUTH_TOKEN")}
        env |= {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN_PATH": str(token)}
        head_port, dashboard_port, *ports = _free_ports(2 + len(RAY_NODE_PORTS) * len(node_cpus))
        address = None
        nodes = []
        for index, cpus in enumerate(node_cpus):
            nodes.append(folder / f"node{index}")
            command = [ray, "start", "--num-cpus", str(cpus), "--temp-dir", str(nodes[-1]),
                       "--object-store-memory", str(object_store_bytes), "--disable-usage-stats"]
            command += [str(item) for flag, port in zip(RAY_NODE_PORTS, ports[index * len(RAY_NODE_PORTS):])
                        for item in (flag, port)]
            if address is None:
                command += ["--head", "--port", str(head_port), "--include-dashboard", "false",
                            "--dashboard-port", str(dashboard_port)]
            else:
                command += ["--address", address]
            started = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                       start_new_session=True)
            sessions.append(started.pid)
            output = started.communicate()[0]
            if started.returncode:
                raise RuntimeError(f"{' '.join(command)} failed:\n{output}")
            if address is None:
                address = f"{_ray_node_ip(output)}:{head_port}"
        _wait_for_ray_nodes(address, env, len(node_cpus))
        yield address, env, nodes
    finally:
        _stop_sessions(sessions[::-1])
        shutil.rmtree(folder, ignore_errors=True)


def _free_ports(count: int) -> list:
    """``count`` distinct TCP ports free now (bound together, then released)."""
    import socket

    sockets = [socket.socket() for _ in range(count)]
    try:
        for sock in sockets:
            sock.bind(("", 0))
        return [sock.getsockname()[1] for sock in sockets]
    finally:
        for sock in sockets:
            sock.close()


def _ray_node_ip(output: str) -> str:
    """The node IP ``ray start --head`` printed ("Local node IP: 10.0.0.2")."""
    import re

    found = re.search(r"Local node IP: (\S+)", output)
    if not found:
        raise RuntimeError(f"ray start --head printed no node IP:\n{output}")
    return found.group(1)


def _wait_for_ray_nodes(address: str, env: dict, count: int, timeout_s: float = 60.0) -> None:
    """Until ``count`` nodes are alive in the cluster (``ray start --address`` returns
    before its node has registered), by a driver of its own."""
    import subprocess

    code = ("import sys, time, ray; ray.init(address=sys.argv[1], log_to_driver=False, logging_level='ERROR')\n"
            "deadline = time.monotonic() + float(sys.argv[3])\n"
            "while sum(node['Alive'] for node in ray.nodes()) < int(sys.argv[2]):\n"
            "    if time.monotonic() > deadline: sys.exit(f'{sys.argv[2]} nodes not alive in time: {ray.nodes()}')\n"
            "    time.sleep(0.2)\n")
    done = subprocess.run([sys.executable, "-c", code, address, str(count), str(timeout_s)], env=env,
                          capture_output=True, text=True, timeout=timeout_s + 60)
    if done.returncode:
        raise RuntimeError(f"the Ray cluster at {address} did not come up:\n{done.stderr[-3000:]}")


def _session_processes(sessions: list) -> dict:
    """Live processes in any of ``sessions``: id -> name (Linux: /proc/PID/stat)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            name, fields = (entry / "stat").read_text().rsplit(")", 1)
        except (OSError, ValueError):
            continue
        fields = fields.split()
        if fields[0] != "Z" and int(fields[3]) in sessions:
            found[int(entry.name)] = name.split("(", 1)[1]
    return found


def _stop_sessions(sessions: list) -> None:
    """Stop every process of ``sessions`` in ``ray stop``'s order: the raylets, then the
    rest but the GCS, then the GCS (each: SIGTERM, then SIGKILL to those left after
    RAY_STOP_GRACE_S)."""
    import signal
    import time

    for bucket in (lambda name: name == "raylet", lambda name: name != "gcs_server", lambda name: True):
        chosen = [pid for pid, name in _session_processes(sessions).items() if bucket(name)]
        for pid in chosen:
            _signal(pid, signal.SIGTERM)
        deadline = time.monotonic() + RAY_STOP_GRACE_S
        while set(chosen) & set(_session_processes(sessions)) and time.monotonic() < deadline:
            time.sleep(0.1)
        for pid in set(chosen) & set(_session_processes(sessions)):
            _signal(pid, signal.SIGKILL)


def _signal(pid: int, number: int) -> None:
    try:
        os.kill(pid, number)
    except ProcessLookupError:  # gone meanwhile
        pass


RAY_CHUNK_TASK = "_ray_chunk"  # core.bank.executors' Ray task: one per chunk


def ray_tasks_per_node(nodes: list, task: str = RAY_CHUNK_TASK) -> list:
    """How many ``task`` tasks each node of ``local_ray_cluster`` (its folders) has run,
    read from Ray's own per-node logs: a Ray worker writes the line ":task_name:<task>"
    to its <temp-dir>/session_latest/logs/worker-*.out as each task starts (the log
    monitor reads it to label output)."""
    marker = f":task_name:{task}"
    return [sum(line == marker for path in Path(node).glob("session_latest/logs/worker-*.out")
                for line in path.read_text(errors="replace").splitlines()) for node in nodes]
