"""The bank report: paper-style quality statistics of an exported bank, optionally side
by side with a real ground-truth database, written as OUT/report.md and OUT/report.png.

Statistics per class (the dataset's class names; bank and real database matched by name):

- kept: entries in the database; dropped: scanned poses with fewer than min_points
  points in the box (bank only);
- points per entry: median, p10 and p90 of the kept entries (numpy's linear quantiles);
- points by distance: the median points per entry in rings of DISTANCE_RING m of
  box-centre distance from the sensor, hypot(x, y);
- intensity: histogram of every kept point's intensity, folder.INTENSITY_BINS equal
  bins over the dataset's range [0, INTENSITY_MAX] (KITTI 0..1, nuScenes/Lyft 0..255);
- coverage: 2-D histogram of kept box centres (x, y) in cells of the grid step,
  centred on the grid's nodes (sensor frame, metres); centres beyond them are not counted.

A bank's statistics come from its chunk records and identity (OUT/.work), read one
record at a time, and every distribution is kept as a histogram (points per entry are
integers: the quantiles stay exact), so memory and time are flat in the bank's size. A
real database is counted from its info pickle and .bin files, one file at a time.
"""

import io
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_output, read_float32_rows
from ..scan.sensors import BIN_COLUMNS, INTENSITY_MAX
from .config import DATASET_GRIDS, grid_values
from .folder import INTENSITY_BINS, WORK, chunk_record, chunk_record_path, read_identity
from .formats import DATABASE_CLASSES
from ..gt_database import database_convention, load_infos

DISTANCE_RING = 10.0  # m: width of the distance bins
QUANTILES = (0.5, 0.1, 0.9)  # median, p10, p90
REPORT_MD, REPORT_PNG = "report.md", "report.png"
DPI = 100  # fixed, so the PNG is the same bytes for the same statistics


class ClassCounts:
    """Running statistics of one class, as histograms (flat in the number of entries)."""

    def __init__(self, coverage_edges: tuple):
        self.coverage_edges = coverage_edges  # (x edges, y edges) m
        self.kept, self.dropped = 0, 0
        self.points = np.zeros(1, np.int64)  # [n]: kept entries with n points
        self.rings = {}  # ring index -> histogram of points per entry, like ``points``
        self.intensity = np.zeros(INTENSITY_BINS, np.int64)
        self.coverage = np.zeros((len(coverage_edges[0]) - 1, len(coverage_edges[1]) - 1), np.int64)

    def add_entries(self, points: np.ndarray, x: np.ndarray, y: np.ndarray) -> None:
        """Count kept entries: (N,) points per entry and (N,) box centres x, y (m)."""
        if not len(points):
            return
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        self.kept += len(points)
        self.points = _add_histogram(self.points, points)
        rings = np.floor(np.hypot(x, y) / DISTANCE_RING).astype(np.int64)
        for ring in np.unique(rings):
            self.rings[int(ring)] = _add_histogram(self.rings.get(int(ring), np.zeros(1, np.int64)),
                                                   points[rings == ring])
        self.coverage += np.histogram2d(x, y, self.coverage_edges)[0].astype(np.int64)

    def summary(self, intensity_edges: np.ndarray, real: bool) -> dict:
        """Plain values: kept, dropped (None for a real database), points {median, p10,
        p90} (None without entries), distance [{from_m, to_m, entries, median}] over the
        non-empty rings, intensity (INTENSITY_BINS,) int64 counts and intensity_mean
        (from the bin centres; None without points), coverage (nx, ny) int64 counts."""
        centres = (intensity_edges[:-1] + intensity_edges[1:]) / 2
        total = int(self.intensity.sum())
        return {
            "kept": self.kept, "dropped": None if real else self.dropped,
            "points": dict(zip(("median", "p10", "p90"), _quantiles(self.points))),
            "distance": [{"from_m": ring * DISTANCE_RING, "to_m": (ring + 1) * DISTANCE_RING,
                          "entries": int(histogram.sum()), "median": _quantiles(histogram)[0]}
                         for ring, histogram in sorted(self.rings.items())],
            "intensity": self.intensity.copy(),
            "intensity_mean": float(centres @ self.intensity / total) if total else None,
            "coverage": self.coverage.copy(),
        }


def _add_histogram(histogram: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``histogram`` (counts per non-negative integer) plus the non-empty integers
    ``values``: updated in place, or grown (at least doubled) when a value passes its
    end. Time O(len(values)) amortised, whatever the histogram's length."""
    values, counts = np.unique(values, return_counts=True)
    if values[-1] >= len(histogram):
        histogram = np.concatenate([histogram, np.zeros(max(values[-1] + 1, 2 * len(histogram)) - len(histogram),
                                                        np.int64)])
    histogram[values] += counts
    return histogram


def _quantiles(histogram: np.ndarray) -> list:
    """QUANTILES of the integers counted by ``histogram``, as np.quantile's linear rule
    gives them for the values themselves; Nones when it counts nothing."""
    cumulative = np.cumsum(histogram)
    if cumulative[-1] == 0:
        return [None] * len(QUANTILES)
    position = (cumulative[-1] - 1) * np.asarray(QUANTILES)
    low = np.floor(position)
    below = np.searchsorted(cumulative, low, side="right")  # the sorted value at rank ``low``
    above = np.searchsorted(cumulative, np.minimum(low + 1, cumulative[-1] - 1), side="right")
    return [float(value) for value in below + (position - low) * (above - below)]


def coverage_edges(x_range, y_range) -> tuple:
    """(x edges, y edges) m of cells one grid step wide centred on the grid's nodes, for
    grid ranges [start, stop, step] m."""
    def edges(start, stop, step):
        nodes = grid_values(start, stop, step)
        return np.append(nodes - step / 2, nodes[-1] + step / 2)
    return edges(*x_range), edges(*y_range)


def _intensity_edges(dataset: str) -> np.ndarray:
    """(INTENSITY_BINS + 1,) bin edges over the dataset's intensity range."""
    return np.linspace(0.0, INTENSITY_MAX[dataset], INTENSITY_BINS + 1)


def _statistics(source, dataset: str, config, edges: tuple, classes: dict) -> dict:
    """The statistics dict shared by banks and real databases (see bank_statistics)."""
    intensity_edges = _intensity_edges(dataset)
    return {"source": str(source), "dataset": dataset, "config": config, "intensity_edges": intensity_edges,
            "coverage_edges": edges,
            "classes": {name: counts.summary(intensity_edges, real=config is None)
                        for name, counts in sorted(classes.items())}}


def bank_statistics(out) -> dict:
    """Statistics of the bank in folder ``out``, from OUT/.work (identity and chunk
    records, streamed one at a time; no .bin file is read).

    Returns {"source": str(out), "dataset", "config" (the identity's), "intensity_edges"
    (INTENSITY_BINS + 1,) in the dataset's intensity unit, "coverage_edges" (x edges,
    y edges) m, "classes": {name: ClassCounts.summary()}} with every class of the bank,
    sorted by name. InputError when ``out`` holds no identity or misses chunk records.
    """
    out = Path(out)
    ident = read_identity(out)
    config = ident["config"]
    class_of_object = np.asarray(ident["class_names"])
    edges = coverage_edges(config["x"], config["y"])
    classes = {name: ClassCounts(edges) for name in set(ident["class_names"])}
    for record in _chunk_records(out, ident["chunks"]):
        stats = record["stats"]
        names = class_of_object[stats["object"]]
        for name in np.unique(names):
            mine = stats[names == name]
            kept = mine[mine["kept"]]
            classes[name].dropped += len(mine) - len(kept)
            classes[name].add_entries(kept["points"], kept["x"], kept["y"])
        for name, histogram in record["intensity"].items():
            classes[name].intensity += histogram
    return _statistics(out, config["dataset"], config, edges, classes)


def _chunk_records(out: Path, chunk_count: int):
    """Yield the chunk records of ``out`` in chunk order, one at a time; InputError
    when any is missing (checked before the first) or damaged."""
    paths = [chunk_record_path(out, chunk_id) for chunk_id in range(chunk_count)]
    missing = [path for path in paths if not path.is_file()]
    if missing:
        raise InputError(out, f"{len(missing)} of {chunk_count} chunk records missing under {WORK}/chunks "
                              f"(first: {missing[0].name}); finish the export (--resume) first")
    for chunk_id, path in enumerate(paths):
        record = chunk_record(out, chunk_id)
        if record is None:
            raise InputError(path, "a damaged chunk record; export_bank.py --resume redoes it")
        yield record


def real_statistics(info_pickle, root=None, *, dataset: str, grid=None, convention: str | None = None) -> dict:
    """The statistics of bank_statistics for a real OpenPCDet/mmdetection3d database.

    info_pickle: ``{class: [info]}`` (``*_dbinfos_*.pkl``); each info's ``path`` is
    joined to ``root`` (default: the pickle's folder). Each .bin holds float32 rows of
    the dataset's columns (KITTI 4, nuScenes/Lyft 5), intensity the fourth. Distances
    and coverage from box3d_lidar x, y; coverage cells from ``grid`` = (x range, y
    range) as [start, stop, step] m (default: the dataset's grid). "dropped" is None
    and "config" None. InputError names an unreadable pickle or .bin file, or a pickle
    none of whose classes is one of ``dataset``'s (another dataset's database; nuScenes
    and Lyft share most names, so those two are not told apart), or whose infos
    contradict a stated ``convention`` (gt_database.database_convention: the score read
    after the export would refuse it).
    """
    info_pickle = Path(info_pickle)
    root = Path(root) if root is not None else info_pickle.parent
    if dataset not in BIN_COLUMNS:
        raise ValueError(f"unknown dataset {dataset!r} (known: {', '.join(BIN_COLUMNS)})")
    infos = load_infos(info_pickle)
    database_convention(info_pickle, infos, convention)
    held = sorted(name for name, entries in infos.items() if entries)
    if held and not set(held) & set(DATABASE_CLASSES[dataset]):  # its .bin rows would not be the dataset's either
        raise InputError(info_pickle, f"holds no {dataset} class (it has {', '.join(held[:4])}"
                                      f"{', ...' if len(held) > 4 else ''}): the database of another dataset? The "
                                      f"bank is {dataset}; choose a {dataset} database")
    edges = coverage_edges(*(grid or DATASET_GRIDS[dataset]))
    classes = {}
    for name, entries in infos.items():
        if not entries:  # databases list every class of the dataset, also the ones they lack
            continue
        counts = classes[name] = ClassCounts(edges)
        points = np.zeros(len(entries), np.int64)
        for index, info in enumerate(entries):
            rows = read_float32_rows(root / info["path"], len(BIN_COLUMNS[dataset]),
                                     f"values ({dataset} database columns)", int(info["num_points_in_gt"]))
            points[index] = len(rows)
            counts.intensity += np.histogram(rows[:, 3], INTENSITY_BINS, (0.0, INTENSITY_MAX[dataset]))[0]
        centres = np.array([np.asarray(info["box3d_lidar"], np.float32)[:2] for info in entries],
                           np.float32).reshape(-1, 2)
        counts.add_entries(points, centres[:, 0], centres[:, 1])
    return _statistics(info_pickle, dataset, None, edges, classes)


def real_reference(real, config: dict, real_root=None, convention: str | None = None) -> dict:
    """real_statistics of the database ``real`` (.bin files under ``real_root``, stored
    in ``convention``, None: read from it) for a bank made with ``config`` (its dataset
    and grid), to set beside it in the report."""
    return real_statistics(real, real_root, dataset=config["dataset"], grid=(config["x"], config["y"]),
                           convention=convention)


def write_report(out, reference: dict | None = None, quality: dict | None = None) -> tuple:
    """Write OUT/report.md and OUT/report.png for the bank in ``out``, side by side with
    a real database's ``reference`` (real_reference) when given, with its quality score
    ``quality`` (quality.score.score_bank: a table and a plot) when given. Every statistic is
    computed before anything is written and each file is written atomically, so bad
    input (InputError) leaves no report file. The same bank gives the same bytes.
    Without matplotlib (Blender's own Python) there is no figure: report.md says so.
    Returns (md path, png path or None)."""
    out = Path(out)
    bank = bank_statistics(out)
    try:
        figure = _figure_png(bank, reference, quality)
    except ImportError:
        figure = None
    markdown = _markdown(bank, reference, quality, figure is not None)
    outputs = {out / REPORT_MD: markdown.encode(errors="surrogateescape")}  # a folder name not UTF-8: its bytes
    if figure is not None:
        outputs[out / REPORT_PNG] = figure
    for path, data in outputs.items():
        with atomic_output(path) as stream:
            stream.write(data)
    return out / REPORT_MD, out / REPORT_PNG if figure is not None else None


# Markdown

NONE = "–"


def _number(value) -> str:
    """``value`` with thousands separators and at most one decimal; NONE for None."""
    return NONE if value is None else f"{value:,.1f}".removesuffix(".0")


def _table(header: list, rows: list) -> list:
    """Markdown table lines: the first column left-aligned, the others right-aligned."""
    return [f"| {' | '.join(header)} |", "|" + "---|" + "---:|" * (len(header) - 1),
            *(f"| {' | '.join(row)} |" for row in rows)]


def _settings_line(bank: dict) -> str:
    """The dataset, sensor, grid and seed of the bank's config, in one sentence."""
    config = bank["config"]
    sensor = (Path(config["sensor"]).name if config["sensor"].endswith(".toml") else config["sensor"]) \
        or f"{config['dataset']} (the dataset's)"
    (h0, h1, hs), (x0, x1, xs), (y0, y1, ys) = config["headings_deg"], config["x"], config["y"]
    return (f"Dataset **{config['dataset']}**, sensor **{sensor}**, formats {', '.join(config['formats'])}; "
            f"grid headings {_number(h0)}..{_number(h1)} deg step {_number(hs)}, x {_number(x0)}..{_number(x1)} m "
            f"step {_number(xs)}, y {_number(y0)}..{_number(y1)} m step {_number(ys)}, ego clearance "
            f"{_number(config['ego_clearance'])} m; seed **{config['seed']}**; min_points {config['min_points']}.")


def _class_names(bank: dict, real) -> list:
    return sorted(set(bank["classes"]) | set(real["classes"] if real else ()))


def _markdown(bank: dict, real, quality=None, figure: bool = True) -> str:
    """The report's Markdown text (no timestamp, no absolute path: the same statistics
    give the same bytes)."""
    names = _class_names(bank, real)
    sources = [("bank", bank)] + ([("real", real)] if real else [])
    lines = [f"# Bank report: {Path(bank['source']).resolve().name}", "", _settings_line(bank)]
    if real:
        entries = sum(stats["kept"] for stats in real["classes"].values())
        lines.append(f"Real database: `{Path(real['source']).name}` ({real['dataset']}, entries: {entries:,}), "
                     "classes matched by name.")
    lines += ["", f"![bank report]({REPORT_PNG})" if figure else "(No figure: matplotlib is not installed here.)",
              "", "## Entries", ""]
    lines += _table(["class", "bank kept", "bank dropped"] + (["real"] if real else []),
                    [_count_row(name, bank, real) for name in names] + [_count_row(None, bank, real)])
    lines += ["", "## Points per entry", ""]
    lines += _table(["class"] + [f"{label} {q}" for label, _ in sources for q in ("median", "p10", "p90")],
                    [[name] + [_number((_get(source, name, "points") or {}).get(q))
                               for _, source in sources for q in ("median", "p10", "p90")] for name in names])
    lines += ["", "## Median points per entry by distance", ""] + _distance_table(names, sources)
    lines += ["", "## Intensity", ""]
    unit = f"0..{_number(INTENSITY_MAX[bank['dataset']])}"
    lines += _table(["class"] + [f"{label} mean ({unit})" for label, _ in sources],
                    [[name] + [_intensity_mean(source, name) for _, source in sources] for name in names])
    if quality is not None:
        from ..quality.score import table_rows

        lines += ["", "## Quality score against the real database", ""]
        only = ", ".join(quality["unmatched"]) or "none"
        if quality["classes"]:
            lines += _table(*table_rows(quality)) + ["", _QUALITY_NOTE]
            if quality["unmatched"]:
                lines += ["", f"Classes in only one database (not scored): {only}."]
        else:
            lines += [f"No class in common with the real database (classes in only one of them: {only}): "
                      "nothing to score."]
    lines += ["", "## Columns", "", *_COLUMN_NOTES, ""]
    return "\n".join(lines)


def _count_row(name, bank: dict, real) -> list:
    """Kept and dropped bank entries and real entries of class ``name`` (None: the total)."""
    def count(statistics, key):
        if name is None:
            return sum(stats[key] or 0 for stats in statistics["classes"].values())
        return _get(statistics, name, key)
    row = [name or "**total**", _number(count(bank, "kept")), _number(count(bank, "dropped"))]
    return row + ([_number(count(real, "kept"))] if real else [])


def _get(statistics: dict, name: str, key: str):
    """One class's value, None when the class is not in ``statistics``."""
    return statistics["classes"].get(name, {}).get(key)


def _intensity_mean(statistics: dict, name: str) -> str:
    mean = _get(statistics, name, "intensity_mean")
    return NONE if mean is None else f"{mean:.3f}"


def _distance_table(names: list, sources: list) -> list:
    """One row per class and source, one column per ring any of them has: "median (entries)"."""
    rings = sorted({(ring["from_m"], ring["to_m"]) for _, source in sources
                    for stats in source["classes"].values() for ring in stats["distance"]})
    rows = []
    for name in names:
        for label, source in sources:
            found = {(ring["from_m"], ring["to_m"]): ring for ring in _get(source, name, "distance") or []}
            rows.append([name, label] + [f"{_number(found[key]['median'])} ({found[key]['entries']:,})"
                                         if key in found else NONE for key in rings])
    return _table(["class", "source"] + [f"{_number(low)}–{_number(high)} m" for low, high in rings], rows)


_COLUMN_NOTES = (
    "- **kept**: entries in the database (bank: poses with at least min_points points in the box; real: every info).",
    "- **dropped**: bank poses scanned but left out with fewer than min_points points in the box.",
    "- **median, p10, p90**: points per kept entry (numpy's linear quantiles).",
    f"- **distance columns**: box-centre distance from the sensor, hypot(x, y), in {DISTANCE_RING:g} m rings; "
    "each cell is the median points per entry and, in parentheses, the entries in that ring.",
    f"- **intensity mean**: the mean point intensity in the dataset's unit, from the {INTENSITY_BINS}-bin "
    "histogram (bin centres) drawn in the figure.",
    "- **figure**: points per entry vs distance (bank solid, real dashed), intensity densities per class "
    "(bank solid, real dashed), and the bird's-eye coverage of the bank's kept box centres (cells one grid "
    "step wide, centred on the grid's nodes; sensor at the origin).",
    "- **–**: no value (the class is not in that database, or has no entry there).",
)


_QUALITY_NOTE = ("Per class matched by name (docs/formats.md, \"Quality score\"): objects compared, the Fréchet "
                 "distance of the quality encoder's features with its 95 % bootstrap interval (– without torch), "
                 "MMD-CD and COV (Chamfer on box-normalised 64-point objects), 1-NNA (0.5 = indistinguishable), "
                 "W1 of log points scaled to 10 m, W1 of intensity over the dataset's maximum, W1 fill (how the "
                 "points fill their box per axis, box half-sides) and W1 grade (the box bottom's elevation angle "
                 "from the sensor's foot, degrees). Lower is better except COV.")


# Figure

def _figure_png(bank: dict, real, quality=None) -> bytes:
    """The report's PNG: points vs distance, intensity densities, bird's-eye coverage,
    and with ``quality`` the per-class quality scores."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(17 + 6 * (quality is not None), 5), layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots(1, 3 + (quality is not None))
    distance_axes, intensity_axes, coverage_axes = axes[:3]
    if quality is not None:
        _plot_quality(axes[3], quality)
    colors = {name: f"C{index % 10}" for index, name in enumerate(_class_names(bank, real))}
    for label, source, linestyle, marker in (("bank", bank, "-", "o"), ("real", real, "--", "s")):
        for name, stats in (source["classes"].items() if source else ()):
            style = {"color": colors[name], "linestyle": linestyle, "label": f"{name} ({label})"}
            _plot_distance(distance_axes, stats, marker=marker, **style)
            _plot_intensity(intensity_axes, stats, source["intensity_edges"], **style)
    distance_axes.set(xlabel="box-centre distance from the sensor (m)", ylabel="median points per entry",
                      title="Points per entry vs distance")
    intensity_axes.set(xlabel=f"intensity (0..{_number(INTENSITY_MAX[bank['dataset']])})", ylabel="density",
                       title="Intensity per class")
    for axes in (distance_axes, intensity_axes):
        if axes.has_data():
            axes.legend(fontsize="small")
    _plot_coverage(figure, coverage_axes, bank)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI, metadata={"Software": None})
    return buffer.getvalue()


def _plot_distance(axes, stats: dict, **style) -> None:
    """Median points per entry at each ring's centre (symmetric log scale: 0 stays drawable)."""
    rings = stats["distance"]
    if rings:
        axes.plot([(ring["from_m"] + ring["to_m"]) / 2 for ring in rings], [ring["median"] for ring in rings],
                  **style)
        axes.set_yscale("symlog", linthresh=10)


def _plot_intensity(axes, stats: dict, edges: np.ndarray, **style) -> None:
    """The intensity histogram as a normalised density (integral 1)."""
    total = stats["intensity"].sum()
    if total:
        axes.stairs(stats["intensity"] / (total * np.diff(edges)), edges, **style)


def _plot_coverage(figure, axes, bank: dict) -> None:
    """Kept bank entries per cell, all classes, bird's-eye view (sensor frame)."""
    x_edges, y_edges = bank["coverage_edges"]
    coverage = sum(stats["coverage"] for stats in bank["classes"].values())
    mesh = axes.pcolormesh(x_edges, y_edges, coverage.T, cmap="viridis", vmin=0)
    axes.plot(0, 0, "r+", markersize=12)  # the sensor
    axes.set(xlabel="x (m)", ylabel="y (m)", title="Bird's-eye coverage (kept entries)", aspect="equal")
    figure.colorbar(mesh, ax=axes, label="kept entries per cell")


def _plot_quality(axes, quality: dict) -> None:
    """Per class: the feature-free distances as bars (lower is better; COV as 1 - COV and
    1-NNA as 2 |1-NNA - 0.5| so every bar reads the same way, 0 at best), the Fréchet
    distance with its interval on a twin axis."""
    names = list(quality["classes"])
    keys = (("mmd", "MMD-CD", None), ("coverage", "1 - COV", lambda v: 1 - v),
            ("one_nn_accuracy", "2 |1-NNA - 0.5|", lambda v: 2 * abs(v - 0.5)), ("w1_points", "W1 points", None),
            ("w1_intensity", "W1 intensity", None), ("w1_fill", "W1 fill", None),
            ("w1_grade", "W1 grade (deg)", None))
    width = 0.8 / (len(keys) + 1)
    for index, (key, label, reading) in enumerate(keys):
        values = [quality["classes"][name][key] for name in names]  # None: not measured (too few objects)
        values = [np.nan if value is None else reading(value) if reading else value for value in values]
        axes.bar(np.arange(len(names)) + index * width, values, width, label=label)
    frechet = [quality["classes"][name]["frechet"] for name in names]
    if names and all(value is not None for value in frechet):
        twin = axes.twinx()
        low = [value - quality["classes"][name]["frechet_low"] for name, value in zip(names, frechet)]
        high = [quality["classes"][name]["frechet_high"] - value for name, value in zip(names, frechet)]
        twin.errorbar(np.arange(len(names)) + len(keys) * width, frechet, yerr=[low, high], fmt="ks",
                      label="Fréchet (95 % interval)")
        twin.set_ylabel("Fréchet distance")
        twin.legend(fontsize="small", loc="upper right")
    axes.set_xticks(np.arange(len(names)) + len(keys) * width / 2, names)
    axes.set(ylabel="distance (lower is better)", title="Quality score against the real database")
    if axes.has_data():
        axes.legend(fontsize="small", loc="upper left")
