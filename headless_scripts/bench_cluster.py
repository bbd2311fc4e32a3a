"""Parallel efficiency of the bank export on a Ray cluster: the same bank exported by a
1-node and an N-node cluster (each node one CPU), efficiency = T1 / (N x TN), with one
local process (no Ray) as the reference.

    .venv/bin/python headless_scripts/bench_cluster.py [--nodes 2] [--repeats 3] [--quick] [--out bench/cluster]

The clusters are started as docs/user_guide.md tells a user to start one across
machines (dev.local_ray_cluster: ``ray start --head``, then ``ray start --address`` per
other node, token authentication on), every node with --num-cpus 1, but all on this
machine: here "nodes" are separate sets of Ray processes on one machine and its cores,
shared with other work (the load average is recorded with every run), so the figure is
what the Ray executor's scheduling, task and object-transfer overheads leave of N
cores, not a network measurement.

Workload: bench_bank.py's objects and measured exports (each a fresh driver process:
plan, export.run_plan timed, assemble): the Chrono truck chassis (11k faces; the sample
truck when the Chrono data is missing) at nuScenes settings on bench_bank's thinned grid
(600 poses) with chunk_size 16 (38 tasks; --quick: the 108-pose grid, 7 tasks).
Setups: one local process (--executor local --workers 1), a 1-node cluster, an N-node
cluster; --repeats runs each, medians compared. Every run's manifest.json (which
lists every bank file's sha256) is hashed: all runs must give the same bank. Chunks per
node are read from Ray's per-node worker logs (dev.ray_tasks_per_node). Prints a
Markdown table; writes <out>.json, <out>.md, <out>.png. "nodes busy" is the chunks' own
clock (export.ChunkDone) over nodes x wall time: near 100 % with a poor efficiency means
the CPUs ran slower (other work on the cores), not that Ray left nodes idle.
"""

import tempfile
import time
from pathlib import Path

import numpy as np

import bench_bank  # beside this script; it puts addon/ on the import path
from bench_bank import ROOT, export_once, make_objects
from pgt_blender import cli, dev
from pgt_blender.core.scan.targets import resolve_engine


def busy_share(run: dict, nodes: int) -> float:
    """The share of the nodes' time spent inside chunks (the chunks' own stage clock,
    export.ChunkDone, over nodes x the export's wall time): what scheduling and start-up
    leave idle, apart from how fast the CPUs ran."""
    return sum(seconds for stage, seconds in run["stages_s"].items() if stage != "casts") / (nodes * run["export_s"])


def measure(name: str, runs: list, nodes: int, chunks_per_node: list) -> dict:
    seconds = float(np.median([run["export_s"] for run in runs]))
    return {"setup": name, "nodes": nodes, "runs": len(runs), "export_s": seconds,
            "busy_share": float(np.median([busy_share(run, nodes) for run in runs])),
            "all_s": [round(run["export_s"], 2) for run in runs], "kept": runs[0]["kept"],
            "kept_per_s": runs[0]["kept"] / seconds, "chunks_per_node": chunks_per_node,
            "load_1min": [round(run["load_1min"], 2) for run in runs],
            "manifest_sha256": sorted({run["manifest_sha256"] for run in runs})}


def on_cluster(name: str, nodes: int, folders: list, config: dict, repeats: int, scratch: Path) -> dict:
    """``repeats`` exports into ``scratch`` on a fresh cluster of ``nodes`` one-CPU nodes."""
    with dev.local_ray_cluster((1,) * nodes) as (address, env, node_folders):
        runs, per_node = [], []
        for _ in range(repeats):
            before = dev.ray_tasks_per_node(node_folders)
            runs.append(export_once(folders, config, 1, scratch, address, env))
            per_node.append([after - earlier for after, earlier in zip(dev.ray_tasks_per_node(node_folders), before)])
    return measure(name, runs, nodes, per_node)


def plot(rows: list, efficiency: float, nodes: int):
    def draw(plt):
        figure, axes = plt.subplots(figsize=(8, 4.5))
        x = np.arange(len(rows))
        axes.bar(x, [row["export_s"] for row in rows], 0.6, color=["0.6", "C0", "C1"][:len(rows)])
        for index, row in enumerate(rows):
            axes.plot([index] * len(row["all_s"]), row["all_s"], "k.", ms=5)
        axes.set_xticks(x, [row["setup"] for row in rows])
        axes.set(ylabel="export seconds (bar: median, dots: runs)",
                 title=f"bank export on a local Ray cluster: efficiency {efficiency:.2f} on {nodes} nodes")
        return figure
    return draw


def main(argv: list) -> int:
    parser = cli.parser("bench_cluster.py", __doc__)
    parser.add_argument("--nodes", type=int, default=2, help="nodes of the larger cluster, one CPU each")
    parser.add_argument("--repeats", type=int, default=3, help="runs per setup")
    parser.add_argument("--quick", action="store_true", help="a smoke test: 108 poses, 1 run each")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "cluster")
    args = parser.parse_args(argv)
    import ray

    repeats = 1 if args.quick else args.repeats
    grid = bench_bank.QUICK_SUBSET if args.quick else bench_bank.SUBSET
    config = grid | {"chunk_size": 16, "engine": resolve_engine("auto")}
    machine = dev.machine(numpy=np.__version__, ray=ray.__version__, engine=config["engine"])
    print(f"machine: {machine}\n", flush=True)
    load_before, started = dev.load_average(), time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_cluster_objects_") as scratch:
        scratch = Path(scratch)
        objects = make_objects(scratch, bench_bank.CHRONO_TRUCK, subdivided=False)
        name = next(iter(objects))
        folders = [objects[name]["folder"]]
        local = [export_once(folders, config, 1, scratch) for _ in range(repeats)]
        rows = [measure("local, 1 process", local, 1, [])]
        print(f"{rows[-1]['setup']}: {rows[-1]['export_s']:.1f} s", flush=True)
        for nodes in (1, args.nodes):
            rows.append(on_cluster(f"Ray, {nodes} node{'s' * (nodes > 1)} x 1 CPU", nodes, folders, config, repeats,
                                   scratch))
            print(f"{rows[-1]['setup']}: {rows[-1]['export_s']:.1f} s", flush=True)
    one, many = rows[1]["export_s"], rows[2]["export_s"]
    efficiency = one / (args.nodes * many)
    same = len({digest for row in rows for digest in row["manifest_sha256"]}) == 1
    line = (f"parallel efficiency on {args.nodes} nodes: T1 / ({args.nodes} x T{args.nodes}) = {one:.1f} / "
            f"({args.nodes} x {many:.1f}) = {efficiency:.2f} (speed-up {one / many:.2f}x); every run the same bank: "
            f"{'yes' if same else 'NO'}")
    body = dev.markdown_table(
        ["setup", "runs", "s (median)", "runs s", "kept", "kept/s", "speed-up vs 1 node", "nodes busy",
         "chunks per node per run", "load 1-min"],
        [[row["setup"], row["runs"], f"{row['export_s']:.2f}", ", ".join(map(str, row["all_s"])), f"{row['kept']:,}",
          f"{row['kept_per_s']:.0f}", f"{one / row['export_s']:.2f}x" if row["chunks_per_node"] else "-",
          f"{row['busy_share']:.0%}", "; ".join("/".join(map(str, run)) for run in row["chunks_per_node"]) or "-",
          ", ".join(map(str, row["load_1min"]))] for row in rows], "lrrrrrrrll")
    inputs = {"object": f"{name}: {objects[name]['source']}; {objects[name]['points']:,} points",
              "config": f"BankConfig() (nuScenes) with {config}",
              "nodes": "separate `ray start` process sets on this one machine (its cores shared), each --num-cpus 1, "
                       "token authentication on; every export a fresh driver process",
              "run": f"{time.perf_counter() - started:.0f} s; load average before {load_before}, after "
                     f"{dev.load_average()} (a machine shared with other work: the times are upper bounds)"}
    print(f"\n{body}\n{line}")
    dev.write_report(args.out, "Bank export on a Ray cluster: parallel efficiency", "bench_cluster.py", machine,
                     inputs, f"**{line}**\n\n{body}",
                     {"machine": machine, "inputs": inputs, "setups": rows, "efficiency": efficiency,
                      "speed_up": one / many, "same_bank": same}, plot(rows, efficiency, args.nodes))
    return 0 if same else 1


if __name__ == "__main__":
    cli.exit(cli.run_main(main, cli.script_argv()))
