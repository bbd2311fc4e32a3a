"""Mix a real ground-truth database with a pseudo-object bank into a new info pickle.

OpenPCDet and mmdetection3d both read an info pickle ``*_dbinfos_*.pkl`` as
``dict[class_name] -> list[info]``, and their samplers draw uniformly from each class
list: the proportions within a list are the sampling proportions. A GT:PGT ratio
``gt:pgt`` therefore means, per class of the real database: every real info once, in
its order, followed by ``round(n_real * pgt / gt)`` bank infos of that class (Python's
round: halves go to the even number), drawn without replacement and kept in the
bank's order. 1:1 (the paper's best) doubles each class list; 1:0 copies the real
database. When the bank holds fewer, all of them go in and the summary gives the
effective ratio. Bank classes the real database lacks are skipped: the detector
config names the classes it samples, and those come from the real data. Bank infos of
KITTI difficulty -1 (out of camera 2's view), which every stock KITTI config drops
before sampling (``filter_by_difficulty: [-1]``), are never drawn: they would only
dilute the ratio.

Paths: the framework joins an info's ``path`` to the dataset root (OpenPCDet
``root_path / path``, mmdet3d ``os.path.join(data_root, path)``). Real infos are kept
as they are. Bank paths are relative to the bank's data root (folder.info_path_root:
the pickle's folder unless the bank was assembled with one); in the output they
are relative to ``root`` (default: the real pickle's folder) when the file lies under
it, else absolute (joining an absolute path yields it, in both frameworks).

The real and bank pickles are only read; the output appears complete or not at all.
"""

import pickle
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import apart_from_inputs, atomic_output
from ..gt_database import CONVENTION_NOTES, detected_convention, load_infos
from .folder import info_path_root

BOX_LAYOUTS = {7: "KITTI layout", 9: "nuScenes layout"}
MAX_PGT_PER_GT = 1000.0  # a bank entry per real one is the paper's 1:1; beyond this, a typo


def parse_ratio(text: str) -> tuple:
    """``text`` is ``"GT:PGT"``, e.g. ``"1:1"``, ``"2:1"``, ``"1:0.5"``; returns
    ``(gt, pgt)`` as floats. GT must be positive, PGT zero or positive; anything else
    raises ValueError naming ``text``."""
    return _checked_ratio(str(text).split(":"), text)


def _checked_ratio(ratio, text) -> tuple:
    """``ratio`` as ``(gt, pgt)`` floats, or ValueError naming ``text``."""
    try:
        gt, pgt = (float(value) for value in ratio)  # a wrong count is a ValueError too
    except (TypeError, ValueError):
        raise ValueError(f"ratio '{text}': expected GT:PGT such as 1:1, 2:1 or 1:0.5") from None
    if not (np.isfinite(gt) and np.isfinite(pgt) and gt > 0 and pgt >= 0):
        raise ValueError(f"ratio '{text}': GT must be a positive number and PGT a number >= 0")
    if not pgt / gt <= MAX_PGT_PER_GT:
        raise ValueError(f"ratio '{text}': at most {MAX_PGT_PER_GT:g} PGT entries per GT entry")
    return gt, pgt


def mix_databases(real_path, bank_path, out_path, ratio=(1.0, 1.0), seed=0, root=None) -> dict:
    """Write a new info pickle: the real database plus bank infos at ``ratio``.

    real_path: the real ground-truth info pickle (``*_dbinfos_*.pkl``); only read.
    bank_path: the bank's info pickle; its paths are relative to its folder. Only read.
    out_path:  the pickle to write (atomically); must be neither input.
    ratio:     ``(gt, pgt)``, e.g. ``parse_ratio("1:1")``; bank infos per class =
               round(n_real * pgt / gt), drawn from those not of difficulty -1.
    seed:      seed of the one ``np.random.default_rng`` drawing every class (sorted
               by name), so a seed gives the same bytes every time.
    root:      the dataset root the framework joins info paths to (default: the real
               pickle's folder); bank files under it get paths relative to it.

    Returns the summary: ``{"classes": {name: {"real", "requested", "bank_available",
    "bank_used", "effective_ratio"}}, "total": {same keys}, "skipped": [bank classes
    not in the real database], "ratio": [gt, pgt], "seed", "out"}``; effective_ratio
    is bank_used / real (PGT per GT; None for an empty class). Bad input raises
    InputError naming the file, and nothing is written then; so does a bank with no
    entry of a real class (unless ``pgt`` is 0).
    """
    real_path, bank_path, out_path = Path(real_path), Path(bank_path), Path(out_path)
    gt, pgt = _checked_ratio(ratio, ratio)
    apart_from_inputs(out_path, (real_path, bank_path))
    if out_path.is_dir():
        raise InputError(out_path, "is a folder; expected the path of the .pkl to write")
    root = Path(root) if root is not None else real_path.parent
    if not root.is_dir():
        raise InputError(root, "the dataset root is not a folder")

    real, bank = load_infos(real_path), load_infos(bank_path)
    _check_compatible(real_path, real, bank_path, bank)
    if pgt > 0 and not any(real.get(name) and infos for name, infos in bank.items()):
        have = ", ".join(sorted(name for name, infos in bank.items() if infos)) or "none"
        raise InputError(bank_path, f"has no entry of a class {real_path.name} has (bank classes: {have}): "
                                    f"nothing to mix")

    rng = np.random.default_rng(seed)
    chosen, classes = {}, {}
    for name in sorted(real):
        sampled = _sampled(bank.get(name, []))
        requested = round(len(real[name]) * pgt / gt)
        # Sorted indices: the drawn entries keep the bank's order.
        chosen[name] = sampled[np.sort(rng.choice(len(sampled), size=min(requested, len(sampled)), replace=False))]
        classes[name] = _counts(len(real[name]), requested, len(sampled), len(chosen[name]))

    merged = _merge(real, bank, chosen, info_path_root(bank_path).resolve(), root.resolve())
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(out_path) as stream:
        pickle.dump(merged, stream)

    totals = [sum(counts[key] for counts in classes.values())
              for key in ("real", "requested", "bank_available", "bank_used")]
    return {"classes": {name: classes[name] for name in real}, "total": _counts(*totals),
            "skipped": sorted(name for name, infos in bank.items() if infos and name not in real),
            "ratio": [gt, pgt], "seed": seed,
            "out": str(out_path)}


def _sampled(infos: list) -> np.ndarray:
    """Indices of the ``infos`` a stock sampler keeps: all but KITTI difficulty -1."""
    return np.array([index for index, info in enumerate(infos) if info.get("difficulty", 0) != -1], np.int64)


def _counts(real: int, requested: int, available: int, used: int) -> dict:
    return {"real": real, "requested": requested, "bank_available": available, "bank_used": used,
            "effective_ratio": used / real if real else None}


def _merge(real: dict, bank: dict, chosen: dict, bank_root: Path, root: Path) -> dict:
    """Real class lists (same info objects, same order) with the chosen bank infos
    appended as copies: path rewritten, group_id following the real database."""
    real_ids = [info["group_id"] for infos in real.values() for info in infos if "group_id" in info]
    # mmdet3d numbers groups over the whole database; bank objects are alone in theirs.
    next_id = int(max(real_ids)) + 1 if real_ids else None
    merged = {}
    for name, infos in real.items():
        added = []
        for index in chosen[name]:
            info = dict(bank[name][index], path=_output_path(bank[name][index]["path"], bank_root, root))
            if next_id is None:
                info.pop("group_id", None)  # the real database's format has none
            else:
                info["group_id"], next_id = next_id, next_id + 1
            added.append(info)
        merged[name] = infos + added
    return merged


def _output_path(path, bank_root: Path, root: Path) -> str:
    """A bank info path (relative to ``bank_root``, or absolute) as the output stores
    it: relative to ``root`` when the file lies under it, else absolute."""
    # Resolved on both sides, so a symlinked folder does not hide that the file is under root.
    file = (bank_root / path).resolve()
    return file.relative_to(root).as_posix() if file.is_relative_to(root) else str(file)


def _check_compatible(real_path: Path, real: dict, bank_path: Path, bank: dict) -> None:
    """The bank's infos must fit the real database's format: the same framework's
    points (detected_convention), the same box length and every key all real infos carry (the
    samplers read them: difficulty, bbox, ...), except group_id, which the merge assigns."""
    real_convention, bank_convention = detected_convention(real), detected_convention(bank)
    if None not in (real_convention, bank_convention) and real_convention != bank_convention:
        raise InputError(bank_path, f"holds {CONVENTION_NOTES[bank_convention]} but the real database "
                                    f"({real_path.name}) holds {CONVENTION_NOTES[real_convention]}: the sampler would "
                                    f"shift every bank object by half its height; mix the bank's "
                                    f"{real_convention}/ pickle")
    real_length, bank_length = _box_length(real_path, real), _box_length(bank_path, bank)
    if None not in (real_length, bank_length) and real_length != bank_length:
        raise InputError(bank_path, f"boxes have {_layout(bank_length)} but the real database's "
                                    f"({real_path.name}) have {_layout(real_length)}")
    real_infos = [info for infos in real.values() for info in infos]
    shared = set.intersection(*(set(info) for info in real_infos)) - {"group_id"} if real_infos else set()
    for name, infos in bank.items():
        for index, info in enumerate(infos):
            missing = sorted(shared - set(info))
            if missing:
                raise InputError(bank_path, f"info {index} of '{name}' lacks {', '.join(missing)}, "
                                            f"which every info of {real_path.name} has")


def _box_length(path: Path, infos: dict):
    """The number of values per box3d_lidar in ``infos`` (None when empty)."""
    lengths = {int(np.size(info["box3d_lidar"])) for entries in infos.values() for info in entries}
    if len(lengths) > 1:
        raise InputError(path, f"box3d_lidar lengths differ within the file: {sorted(lengths)}")
    return lengths.pop() if lengths else None


def _layout(length: int) -> str:
    return f"{length} values" + (f" ({BOX_LAYOUTS[length]})" if length in BOX_LAYOUTS else "")
