"""A bank's quality score against a real ground-truth database, per class matched by
name: scores(bank, real) -> {class: {metric: value}} (metrics.py for each metric).

Each class's entry: bank_objects and real_objects (the objects compared), frechet with
frechet_low and frechet_high (its bootstrap interval; None without an encoder), mmd,
coverage, one_nn_accuracy, w1_points, w1_intensity, w1_fill, w1_grade. Classes of only one side are left
out (``unmatched`` lists them). Every draw is seeded: the same inputs and seed give the
same numbers.
"""

import hashlib
from pathlib import Path

import numpy as np

from ..bank.folder import WORK
from ..progress import progress_bar
from . import metrics
from .sets import PAPER_REFERENCE_SIZE, bank_database, database_sets

# Objects per class and side at most (a seeded draw): the Chamfer metrics cost
# bank x real pairs, so larger classes are drawn down, about the paper's 593.
MAX_OBJECTS = 600

ENCODER_CACHE = "quality_encoder.pt"  # under the bank's OUT/.work when no --encoder is given
METRICS = ("bank_objects", "real_objects", "frechet", "frechet_low", "frechet_high", "mmd", "coverage",
           "one_nn_accuracy", "w1_points", "w1_intensity", "w1_fill", "w1_grade")


def encoder_key(real_sets: dict, dataset: str, seed: int) -> str:
    """What a cached encoder must have been trained from: the very objects it learns
    (``real_sets``' classes, points, intensities and distances: whatever pickle, root,
    convention and sampling they came from) and the training settings."""
    from .encoder import FORMAT, STEPS

    digest = hashlib.sha256(f"{FORMAT} {dataset} {seed} {STEPS}".encode())
    for name in sorted(real_sets):
        found = real_sets[name]
        digest.update(name.encode())
        for values in (found.xyz, found.intensity, found.distance):
            digest.update(np.ascontiguousarray(values).tobytes())
    return digest.hexdigest()


def score_bank(bank, real, convention: str | None = None, real_root=None, encoder=None, learned: bool = True,
               reference: str = "all", limit: int | None = None, seed: int = 0, progress: bool = False) -> dict:
    """{"dataset", "classes": {class: {metric: value}}, "unmatched": [names],
    "encoder": checkpoint path or None} for the bank folder ``bank`` against the real
    info pickle ``real`` (``convention``, checked and by default read from its infos:
    gt_database.database_convention; files under ``real_root``, default its folder;
    ``reference`` and ``limit``: sets.database_sets for the real side, ``limit``
    defaulting to 593 for "dense" and MAX_OBJECTS for "all"; the bank's classes are
    drawn down to MAX_OBJECTS too). ``encoder``: a
    checkpoint; without one and with ``learned``, one is trained on the real database
    and cached in the bank's .work folder (reused while the real objects it learns and
    the settings are unchanged: encoder_key). ``learned`` False (or torch missing, see ``quality_available``)
    leaves the Fréchet values None."""
    info_pickle, bank_convention, dataset, bank_root = bank_database(bank)
    with progress_bar(progress, None, " objects", leave=False) as bar:
        step = bar.update if bar is not None else None
        real_sets = database_sets(real, convention, dataset, real_root, reference, seed,
                                  limit or (PAPER_REFERENCE_SIZE if reference == "dense" else MAX_OBJECTS),
                                  progress=step)
        bank_sets = database_sets(info_pickle, bank_convention, dataset, bank_root, seed=seed, limit=MAX_OBJECTS,
                                  progress=step)
    matched = sorted(set(bank_sets) & set(real_sets))
    model = None  # no encoder is loaded or trained when no class can be compared
    if matched and encoder is not None:
        from .encoder import QualityEncoder
        model = QualityEncoder.load(encoder)
    elif matched and learned:
        from .encoder import STEPS, cached_encoder
        with progress_bar(progress, STEPS, " steps", leave=False) as bar:
            model = cached_encoder(Path(bank) / WORK / ENCODER_CACHE, real_sets, dataset,
                                   encoder_key(real_sets, dataset, seed), seed,
                                   progress=bar.update if bar is not None else None)
    classes = {name: class_scores(bank_sets[name], real_sets[name], model, seed) for name in matched}
    return {"dataset": dataset, "classes": classes, "unmatched": sorted(set(bank_sets) ^ set(real_sets)),
            "encoder": None if model is None else str(encoder or Path(bank) / WORK / ENCODER_CACHE)}


def class_scores(bank_set, real_set, encoder, seed: int = 0) -> dict:
    """Every metric of one class (see the module docstring)."""
    mmd, coverage = metrics.mmd_coverage(metrics.chamfer_matrix(bank_set.xyz, real_set.xyz))
    found = {"bank_objects": len(bank_set), "real_objects": len(real_set), "frechet": None, "frechet_low": None,
             "frechet_high": None, "mmd": mmd, "coverage": coverage,
             "one_nn_accuracy": metrics.one_nn_accuracy(bank_set.xyz, real_set.xyz, seed),
             "w1_points": metrics.w1_points(bank_set, real_set),
             "w1_intensity": metrics.w1_histograms(bank_set.histogram, real_set.histogram),
             "w1_fill": metrics.w1_fill(bank_set, real_set), "w1_grade": metrics.w1_grade(bank_set, real_set)}
    if encoder is not None:
        bank_features, real_features = encoder.features(bank_set), encoder.features(real_set)
        found["frechet"] = metrics.frechet(bank_features, real_features)
        found["frechet_low"], found["frechet_high"] = metrics.frechet_interval(bank_features, real_features, seed)
    return {key: None if isinstance(value, float) and np.isnan(value) else value  # JSON null, the table's –
            for key, value in found.items()}


def quality_available() -> bool:
    """Whether torch imports (the Fréchet distance needs it; the rest does not)."""
    try:
        import torch  # noqa: F401
    except ImportError:
        return False
    return True


def _value(value, digits: int = 3) -> str:
    return "–" if value is None or (isinstance(value, float) and np.isnan(value)) else f"{value:.{digits}f}"


def table_rows(scores: dict) -> tuple:
    """(header, rows) of the per-class table: objects, Fréchet [interval], MMD, COV,
    1-NNA, W1 points, W1 intensity, W1 fill, W1 grade."""
    header = ["class", "bank", "real", "Fréchet [95 % interval]", "MMD-CD", "COV", "1-NNA", "W1 points",
              "W1 intensity", "W1 fill", "W1 grade (°)"]
    rows = []
    for name, found in scores["classes"].items():
        frechet = _value(found["frechet"])
        if found["frechet"] is not None:
            frechet += f" [{_value(found['frechet_low'])}, {_value(found['frechet_high'])}]"
        rows.append([name, str(found["bank_objects"]), str(found["real_objects"]), frechet, _value(found["mmd"]),
                     _value(found["coverage"], 2), _value(found["one_nn_accuracy"], 2), _value(found["w1_points"]),
                     _value(found["w1_intensity"]), _value(found["w1_fill"]), _value(found["w1_grade"])])
    return header, rows
