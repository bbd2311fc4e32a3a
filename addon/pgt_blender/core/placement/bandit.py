"""Thompson sampling of where objects go (the paper's supplement, "Bandit Algorithm
for Object Placement"): a polar grid of cells around the ego, a Beta(failures + 1,
successes + 1) per cell, cells drawn by Thompson sampling, so objects go mostly where
the detector fails.

Grid, sensor frame: ring k spans horizontal ranges ``[k, k + 1) * range_step`` m out to
``max_range``; sector s spans azimuths ``-pi + [s, s + 1) * azimuth_step`` rad. The
paper's "0.075 x 8 m" is read as 0.075 rad by 8 m (84 sectors by 7 rings to 54 m):
a cell as wide as it is deep at about 100 m, narrower nearer the sensor.

Update (``update``, after the detector has seen a scene), as the supplement defines
success and failure with ``score_threshold`` 0.5: a ground-truth box whose cell holds
a matching prediction (same class, centres within ``match_distance`` m) scoring above
the threshold is a success of its cell; a prediction scoring above the threshold that
matches no ground truth (a negative) is a failure of its own cell. The state is plain
numbers (``state_dict``) to store with a training checkpoint, or a JSON file
(``save`` / ``load``, written atomically).
"""

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import TEXT_LIMIT, atomic_output, regular_file

STATE_FORMAT = "pgt-thompson-cells/1"
MAX_CELLS = 10**7  # range rings x azimuth sectors: a state file of a few hundred MB at most


@dataclass
class ThompsonCells:
    """The bandit's grid and counts: ``failures`` and ``successes`` (rings, sectors) float64."""

    range_step: float = 8.0
    azimuth_step: float = 0.075
    max_range: float = 54.0
    failures: np.ndarray = field(default=None, repr=False)
    successes: np.ndarray = field(default=None, repr=False)

    def __post_init__(self):
        if not (self.range_step > 0 and 0 < self.azimuth_step <= 2 * np.pi and 0 < self.max_range < np.inf
                and self.max_range / self.range_step * 2 * np.pi / self.azimuth_step <= MAX_CELLS):
            raise ValueError(f"Thompson cells need range_step > 0, 0 < azimuth_step <= 2 pi, a finite max_range > 0 "
                             f"and at most {MAX_CELLS:,} cells, got {self.range_step}, {self.azimuth_step}, "
                             f"{self.max_range}")
        shape = (self.rings, self.sectors)
        for name in ("failures", "successes"):
            value = np.zeros(shape) if getattr(self, name) is None else np.asarray(getattr(self, name), np.float64)
            if value.shape != shape or not np.isfinite(value).all() or (value < 0).any():
                raise ValueError(f"{name} must be {shape} counts >= 0, got shape {value.shape}")
            setattr(self, name, value)

    @property
    def rings(self) -> int:
        return int(np.ceil(self.max_range / self.range_step))

    @property
    def sectors(self) -> int:
        return int(np.ceil(2 * np.pi / self.azimuth_step))

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """(N,) flat cell index (ring * sectors + sector) of (N, 2) points; -1 beyond max_range."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        distance = np.hypot(xy[:, 0], xy[:, 1])
        ring = (distance / self.range_step).astype(np.int64)
        sector = np.minimum(((np.arctan2(xy[:, 1], xy[:, 0]) + np.pi) / self.azimuth_step).astype(np.int64),
                            self.sectors - 1)
        return np.where(distance < self.max_range, ring * self.sectors + sector, -1)

    def bounds(self, cells: np.ndarray) -> tuple:
        """(range low, range high, azimuth low, azimuth high) (N,) each, of flat cells."""
        ring, sector = np.divmod(np.asarray(cells, np.int64), self.sectors)
        low = ring * self.range_step
        start = -np.pi + sector * self.azimuth_step
        return low, np.minimum(low + self.range_step, self.max_range), start, np.minimum(start + self.azimuth_step,
                                                                                         np.pi)

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        """(rings * sectors,) one Thompson draw per cell, Beta(failures + 1, successes + 1)."""
        return rng.beta(self.failures.ravel() + 1.0, self.successes.ravel() + 1.0)

    def update(self, gt_boxes: np.ndarray, pred_boxes: np.ndarray, pred_scores: np.ndarray,
               gt_names=None, pred_names=None, score_threshold: float = 0.5, match_distance: float = 2.0) -> None:
        """Count one scene's successes and failures (the module docstring): ``gt_boxes``
        (G, >= 2) and ``pred_boxes`` (P, >= 2) centres x, y in the sensor frame,
        ``pred_scores`` (P,); names (G,) and (P,) compared when both are given."""
        gt = np.asarray(gt_boxes, np.float64).reshape(-1, np.shape(gt_boxes)[-1] if np.size(gt_boxes) else 2)
        pred = np.asarray(pred_boxes, np.float64).reshape(-1, np.shape(pred_boxes)[-1] if np.size(pred_boxes) else 2)
        scores = np.asarray(pred_scores, np.float64).reshape(-1)
        if len(scores) != len(pred):
            raise ValueError(f"{len(pred)} predicted boxes but {len(scores)} scores")
        matches = np.hypot(*(gt[:, None, :2] - pred[None, :, :2]).transpose(2, 0, 1)) <= match_distance
        if gt_names is not None and pred_names is not None:
            matches &= np.asarray(gt_names)[:, None] == np.asarray(pred_names)[None, :]
        confident = scores > score_threshold
        detected = (matches & confident[None, :]).any(axis=1)
        negatives = confident & ~matches.any(axis=0)
        for counts, centres in ((self.successes, gt[detected, :2]), (self.failures, pred[negatives, :2])):
            cells = self.cell_of(centres)
            np.add.at(counts.reshape(-1), cells[cells >= 0], 1.0)

    def state_dict(self) -> dict:
        """The grid and counts as plain numbers (JSON- and pickle-safe)."""
        return {"format": STATE_FORMAT, "range_step": self.range_step, "azimuth_step": self.azimuth_step,
                "max_range": self.max_range, "failures": self.failures.tolist(),
                "successes": self.successes.tolist()}

    @classmethod
    def from_state_dict(cls, state: dict) -> "ThompsonCells":
        if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
            raise ValueError(f"not a Thompson cells state (format {STATE_FORMAT})")
        return cls(state["range_step"], state["azimuth_step"], state["max_range"], state["failures"],
                   state["successes"])

    def save(self, path) -> None:
        """Write the state to ``path`` as JSON, atomically."""
        with atomic_output(path) as stream:
            stream.write(json.dumps(self.state_dict()).encode())

    @classmethod
    def load(cls, path) -> "ThompsonCells":
        """The state ``save`` wrote; InputError naming ``path`` when it is not one."""
        path = regular_file(path, TEXT_LIMIT)
        try:
            return cls.from_state_dict(json.loads(path.read_text()))
        except OSError as error:
            raise InputError(path, f"cannot read the file ({error.strerror or error})") from None
        except (ValueError, KeyError, TypeError, RecursionError) as error:
            raise InputError(path, f"not a Thompson cells state: {error}") from None


class ThompsonFile:
    """The ThompsonCells saved at ``path``, read again whenever the file changes (a
    trainer updates and saves them; every data-loader worker follows through this); fresh
    cells out to ``max_range`` while there is no file yet."""

    def __init__(self, path, max_range: float = 54.0):
        self.path, self.max_range = Path(path), max_range
        self._cells, self._stamp = None, ()

    def cells(self) -> ThompsonCells:
        stamp = self.path.stat().st_mtime_ns if self.path.is_file() else None
        if stamp != self._stamp:
            self._cells = ThompsonCells.load(self.path) if stamp is not None else \
                ThompsonCells(max_range=self.max_range)
            self._stamp = stamp
        return self._cells

