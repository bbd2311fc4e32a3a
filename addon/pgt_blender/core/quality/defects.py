"""The ranking check's banks: one dataset-matched bank and variants with one deliberate
defect each (the paper's Table 4 ablations and common authoring mistakes), built from
the same objects with the bank exporter, so a quality score can be checked to rank
every defect below the matched bank.

- ``3600 columns``: the sensor with 3600 azimuth columns instead of the dataset's
  (the paper's azimuth ablation: more points per object than the real sensor gives);
- ``no range noise``: [scan] range_noise = false;
- ``intensity x4``: every point's intensity times 4, clipped to the dataset's maximum;
- ``boxes +20 %``: every box3d_lidar's dx, dy, dz times 1.2 (points unchanged);
- ``flat ground``: [ground] grade_deg = slope_deg = 0 (no road grade, no pitch or roll).

The last two edit a finished bank's files (its .bin intensities, its info pickle), so
its report statistics (from the chunk records) no longer describe it; the scorer reads
the files.
"""

import pickle
from pathlib import Path

import numpy as np

from ..bank.config import config_from_table
from ..bank.export import export_bank
from ..files import atomic_output, read_float32_rows
from ..scan.sensors import BIN_COLUMNS, INTENSITY_MAX
from .sets import bank_database

MATCHED = "matched"
DEFECTS = ("3600 columns", "no range noise", "intensity x4", "boxes +20 %", "flat ground")
WIDE_COLUMNS = 3600


def _table(base: dict, defect: str, folder: Path) -> dict:
    table = {section: dict(values) for section, values in base.items()}
    if defect == "3600 columns":
        sensor = folder / "sensor_3600.toml"
        sensor.write_text(f'base = "{table["bank"]["dataset"]}"\ncolumns = {WIDE_COLUMNS}\n')
        table["bank"]["sensor"] = str(sensor)
    elif defect == "no range noise":
        table.setdefault("scan", {})["range_noise"] = False
    elif defect == "flat ground":
        table["ground"] = {"grade_deg": 0.0, "slope_deg": 0.0}
    return table


def build_banks(objects: list, base: dict, folder, defects=DEFECTS, workers: int = 1) -> dict:
    """{MATCHED or defect: bank folder} under ``folder``: the bank of config table
    ``base`` (config.config_from_table's layout; its dataset's sensor) and one per
    defect, from the same BankObjects ``objects``."""
    folder = Path(folder)
    banks = {}
    for name in (MATCHED, *defects):
        out = folder / name.replace(" ", "_").replace("%", "pct").replace("+", "")
        out.mkdir(parents=True, exist_ok=True)
        export_bank(objects, config_from_table(_table(base, name, folder)), out, workers=workers, overwrite=True)
        if name == "intensity x4":
            scale_intensity(out, 4.0)
        elif name == "boxes +20 %":
            scale_boxes(out, 1.2)
        banks[name] = out
    return banks


def scale_intensity(out, factor: float) -> None:
    """Multiply the intensity of every .bin of the bank ``out`` by ``factor``, clipped
    to the dataset's maximum."""
    info_pickle, _, dataset, root = bank_database(out)
    columns = len(BIN_COLUMNS[dataset])
    for entries in pickle.loads(Path(info_pickle).read_bytes()).values():
        for info in entries:
            path = root / info["path"]
            rows = read_float32_rows(path, columns).copy()
            rows[:, 3] = np.minimum(rows[:, 3] * factor, INTENSITY_MAX[dataset])
            with atomic_output(path) as stream:
                stream.write(rows.astype(np.float32).tobytes())


def scale_boxes(out, factor: float) -> None:
    """Multiply every box3d_lidar's dx, dy, dz in the bank's info pickle by ``factor``."""
    info_pickle = bank_database(out)[0]
    infos = pickle.loads(Path(info_pickle).read_bytes())
    for entries in infos.values():
        for info in entries:
            info["box3d_lidar"] = np.asarray(info["box3d_lidar"]).copy()
            info["box3d_lidar"][3:6] *= factor
    with atomic_output(info_pickle) as stream:
        stream.write(pickle.dumps(infos))
