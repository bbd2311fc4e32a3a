"""The bank's settings, from a TOML file; every key optional (defaults: the paper's).
Every key with its default and meaning: docs/bank.toml (a test keeps it complete).

Unknown keys and wrong types raise InputError naming the file and the key.
"""

import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..classes import DATASETS
from ..errors import InputError, finite_number
from ..files import TEXT_LIMIT, read_toml, regular_file
from ..scan.raycast import ENGINES
from ..scan.sensors import BIN_COLUMNS, INTENSITY_MAX

FORMATS = ("openpcdet", "mmdet3d")
# Datasets whose released files carry no measured intensity: the lyft-dataset-sdk writes
# a constant 100 in every point file (REFERENCE.md 2), so a bank matches it by default.
DATASET_CONSTANT_INTENSITY = {"lyft": 100.0}

# The paper's perception range per dataset (REFERENCE.md 4): x and y [start, stop, step] m.
DATASET_GRIDS = {
    "nuscenes": ((-50.0, 50.0, 5.0), (-50.0, 50.0, 5.0)),
    "kitti": ((0.0, 70.0, 5.0), (-40.0, 40.0, 5.0)),
    "lyft": ((-80.0, 80.0, 5.0), (-80.0, 80.0, 5.0)),
}


@dataclass(frozen=True)
class BankConfig:
    """Validated bank settings; see the module docstring for each key's meaning."""

    dataset: str = "nuscenes"
    sensor: str = ""
    formats: tuple = FORMATS
    seed: int = 0
    min_points: int = 16
    max_distance: float = 0.0
    sweeps: int = 0
    radius_scale: float = 1.0
    intensity: str | float = "auto"
    intensity_checkpoint: str = ""
    chunk_size: int = 64
    headings_deg: tuple = (-180.0, 180.0, 30.0)
    x: tuple = ()
    y: tuple = ()
    ego_clearance: float = 2.0
    centre_jitter: float = 0.5
    size_jitter: float = 0.05
    size_variants: int = 8
    range_noise: bool = True
    drop_rate: float = 0.0
    ray_drop: bool = True
    max_incidence_deg: float = 90.0
    engine: str = "auto"
    ego_motion: bool = True
    grade_deg: float = 0.69
    slope_deg: float = 1.32
    classes: dict = field(default_factory=dict)

    def __post_init__(self):
        grid_x, grid_y = DATASET_GRIDS.get(self.dataset, DATASET_GRIDS["nuscenes"])
        object.__setattr__(self, "x", tuple(self.x) or grid_x)
        object.__setattr__(self, "y", tuple(self.y) or grid_y)

    @property
    def constant_intensity(self) -> float | None:
        """The value every return's intensity is set to, or None for the model's."""
        if self.intensity == "model":
            return None
        if self.intensity == "auto":
            return DATASET_CONSTANT_INTENSITY.get(self.dataset)
        return float(self.intensity)

    def to_dict(self) -> dict:
        """Plain JSON values: what the manifest records and ``--resume`` compares."""
        return {key: list(value) if isinstance(value, tuple) else value for key, value in asdict(self).items()}


# Bounds that keep a config's arrays and run time finite (a bank at 1,000 entries/s).
MAX_GRID_POSES = 10**8  # headings x positions of one object's grid: over a day of export
MAX_SWEEPS = 100  # the datasets merge 10
MAX_SIZE_VARIANTS = 10_000


# TOML section.key -> BankConfig field and the check of its value.
def _positive_int(value):
    return isinstance(value, int) and not isinstance(value, bool) and value > 0


def _non_negative(value):
    return finite_number(value) and value >= 0


def _grid_range(value):
    if not (isinstance(value, list) and len(value) == 3 and all(finite_number(v) for v in value)):
        return False
    start, stop, step = value
    return step > 0 and stop >= start and (stop - start) / step < MAX_GRID_POSES



_KEYS = {
    "bank.dataset": ("dataset", lambda v: v in DATASETS, f"one of {', '.join(DATASETS)}"),
    "bank.sensor": ("sensor", lambda v: isinstance(v, str) and "\0" not in v, "a preset name or a .toml path"),
    "bank.formats": ("formats", lambda v: isinstance(v, list) and v and set(v) <= set(FORMATS)
                     and len(set(v)) == len(v), f"a non-empty list of {', '.join(FORMATS)}, each once"),
    "bank.seed": ("seed", lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2**31,
                  "an integer 0 .. 2,147,483,647 (as every command's --seed)"),
    "bank.min_points": ("min_points", _positive_int, "an integer >= 1"),
    "bank.max_distance": ("max_distance", _non_negative, "metres >= 0 (0: no filter)"),
    "bank.sweeps": ("sweeps", lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= MAX_SWEEPS,
                    f"an integer in 0 .. {MAX_SWEEPS} (0: the dataset's)"),
    "bank.radius_scale": ("radius_scale", lambda v: finite_number(v) and v > 0, "a number > 0"),
    "bank.intensity": ("intensity", lambda v: v in ("auto", "model") or (finite_number(v) and v >= 0),
                       '"auto", "model" or a number >= 0'),
    "bank.intensity_checkpoint": ("intensity_checkpoint", lambda v: isinstance(v, str) and "\0" not in v, "a path"),
    "bank.chunk_size": ("chunk_size", _positive_int, "an integer >= 1"),
    "grid.headings_deg": ("headings_deg", _grid_range, "[start, stop, step] degrees, step > 0, under 1e8 steps"),
    "grid.x": ("x", _grid_range, "[start, stop, step] metres, step > 0, under 1e8 steps"),
    "grid.y": ("y", _grid_range, "[start, stop, step] metres, step > 0, under 1e8 steps"),
    "grid.ego_clearance": ("ego_clearance", _non_negative, "metres >= 0"),
    "jitter.centre": ("centre_jitter", _non_negative, "metres >= 0"),
    "jitter.size": ("size_jitter", lambda v: finite_number(v) and 0 <= v < 0.5, "a fraction in [0, 0.5)"),
    "jitter.size_variants": ("size_variants", lambda v: _positive_int(v) and v <= MAX_SIZE_VARIANTS,
                             f"an integer in 1 .. {MAX_SIZE_VARIANTS}"),
    "scan.range_noise": ("range_noise", lambda v: isinstance(v, bool), "true or false"),
    "scan.drop_rate": ("drop_rate", lambda v: finite_number(v) and 0 <= v < 1, "a fraction in [0, 1)"),
    "scan.ray_drop": ("ray_drop", lambda v: isinstance(v, bool), "true or false"),
    "scan.max_incidence_deg": ("max_incidence_deg", lambda v: finite_number(v) and 0 < v <= 90, "degrees in (0, 90]"),
    "scan.engine": ("engine", lambda v: v in ENGINES, f"one of {', '.join(ENGINES)}"),
    "scan.ego_motion": ("ego_motion", lambda v: isinstance(v, bool), "true or false"),
    "ground.grade_deg": ("grade_deg", lambda v: finite_number(v) and 0 <= v <= 10, "degrees in [0, 10]"),
    "ground.slope_deg": ("slope_deg", lambda v: finite_number(v) and 0 <= v <= 10, "degrees in [0, 10]"),
}
_SECTIONS = {"bank", "grid", "jitter", "scan", "ground", "classes"}


def load_config(path) -> BankConfig:
    """The BankConfig of a TOML file; relative sensor and checkpoint paths are taken
    relative to the file. A bad file, section, key or value raises InputError."""
    path = regular_file(path, TEXT_LIMIT)
    return config_from_table(read_toml(path), path)


def config_from_table(table: dict, path="bank config") -> BankConfig:
    values = {}
    for section, entries in table.items():
        if section not in _SECTIONS:  # a top-level key (a sensor file's "base") is no section
            found = f"section [{section}]" if isinstance(entries, dict) else f"top-level key {section!r}"
            raise InputError(path, f"unknown {found}: a bank config has only the sections "
                                   f"{', '.join(f'[{name}]' for name in sorted(_SECTIONS))}")
        if not isinstance(entries, dict):
            raise InputError(path, f"{section} must be a [{section}] table")
        if section == "classes":
            bad = [key for key, name in entries.items()
                   if not (isinstance(name, str) and re.fullmatch(r"[A-Za-z0-9_-]{0,64}", name))]
            if bad:
                raise InputError(path, f"classes.{bad[0]} = {entries[bad[0]]!r}: expected a dataset class name "
                                       f"(up to 64 letters, digits, '_' and '-'; \"\" skips the class)")
            values["classes"] = dict(entries)
            continue
        for key, value in entries.items():
            name = f"{section}.{key}"
            if name not in _KEYS:
                known = ", ".join(k for k in _KEYS if k.startswith(section + "."))
                raise InputError(path, f"unknown key {name} (known: {known})")
            attribute, valid, expected = _KEYS[name]
            if not valid(value):
                raise InputError(path, f"{name} = {value!r}: expected {expected}")
            values[attribute] = tuple(value) if isinstance(value, list) else value
    for attribute, is_path in (("sensor", lambda v: v.endswith(".toml")), ("intensity_checkpoint", bool)):
        value = values.get(attribute, "")  # a sensor may be a preset's name; a checkpoint is always a path
        if is_path(value) and not Path(value).is_absolute() and isinstance(path, Path):
            values[attribute] = str((path.parent / value).resolve())
    config = BankConfig(**values)
    poses = np.prod([grid_count(*values) for values in (config.headings_deg, config.x, config.y)], dtype=float)
    if poses > MAX_GRID_POSES:
        raise InputError(path, f"the grid has {poses:.3g} headings x positions per object, more than "
                               f"{MAX_GRID_POSES:.0e}: widen the steps")
    if config.constant_intensity is not None and config.constant_intensity > INTENSITY_MAX[config.dataset]:
        raise InputError(path, f"bank.intensity = {config.intensity!r}: above {config.dataset}'s maximum "
                               f"{INTENSITY_MAX[config.dataset]:g}")
    if config.sweeps > 1 and "time_lag" not in BIN_COLUMNS[config.dataset]:
        raise InputError(path, f"bank.sweeps = {config.sweeps}: {config.dataset} files hold one sweep each, with no "
                               f"time column to keep merged sweeps apart; leave it at 0 (the dataset's 1)")
    if config.constant_intensity is not None and config.intensity_checkpoint:
        raise InputError(path, f"bank.intensity_checkpoint is set but {config.dataset} intensities are the constant "
                               f"{config.constant_intensity:g}; set bank.intensity = \"model\" to use the checkpoint")
    return config


def config_from_dict(values, path="bank config") -> BankConfig:
    """The BankConfig of its ``to_dict`` record (a manifest's ``config``), checked as a
    file's is; InputError naming ``path`` otherwise."""
    if not isinstance(values, dict):
        raise InputError(path, f"config must be an object, got {type(values).__name__}")
    section_of = {attribute: name for name, (attribute, _, _) in _KEYS.items()}
    unknown = sorted(set(values) - set(section_of) - {"classes"})
    if unknown:
        raise InputError(path, f"config has unknown key {unknown[0]!r}")
    tables = {"classes": values["classes"]} if "classes" in values else {}
    for attribute, value in values.items():
        if attribute != "classes":
            section, key = section_of[attribute].split(".")
            tables.setdefault(section, {})[key] = value
    return config_from_table(tables, path)


def config_table(config: BankConfig) -> dict:
    """``config`` as the tables of its TOML file, every key set (config_from_table reads
    them back to the same BankConfig, and checks them as it does a file's)."""
    values = asdict(config)
    sections = {}
    for name, (attribute, _, _) in _KEYS.items():
        section, key = name.split(".")
        value = values[attribute]
        sections.setdefault(section, {})[key] = list(value) if isinstance(value, tuple) else value
    if config.classes:
        sections["classes"] = dict(config.classes)
    return sections


def config_toml(config: BankConfig) -> str:
    """``config`` as the TOML text load_config reads back to the same BankConfig: every
    key written, so the file says all the bank depends on."""
    return "\n\n".join(f"[{section}]\n" + "\n".join(f"{key} = {_toml_value(value)}" for key, value in table.items())
                       for section, table in config_table(config).items()) + "\n"


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)


def grid_count(start: float, stop: float, step: float) -> int:
    """How many values ``grid_values`` gives."""
    return int(np.floor((stop - start) / step + 1e-9)) + 1


def grid_values(start: float, stop: float, step: float) -> np.ndarray:
    """start, start + step, ... up to stop included (to 1e-9 of a step)."""
    return start + step * np.arange(grid_count(start, stop, step))

