"""Train the CycleGAN intensity estimator (paper sec. 3.2 and its supplement). Needs PyTorch.

Domains: rgb objects (K = 3 sRGB) and real LiDAR objects (K = 1 intensity over the
dataset's maximum), both ObjectSets of P points in the normalised box frame. Networks
(model.py): generators G: rgb -> int and F: int -> rgb, discriminators D_int, D_rgb.

Each step draws ``batch`` rgb objects and, for each, a real object of the same class
(the paper trains per class; the data module keeps only classes both domains have):

    fake_int = G(a), fake_rgb = F(b), rec_rgb = F(fake_int), rec_int = G(fake_rgb)
    L_G = (D_int(fake_int) - 1)^2 + (D_rgb(fake_rgb) - 1)^2          LSGAN
          + lambda_cycle (|rec_rgb - a|_1 + |rec_int - b|_1)             cycle
          + L_group(fake_int vs b), weight lambda_group = 0.1            losses.py
    L_D = ((D(real) - 1)^2 + D(fake)^2) / 2 for each discriminator

means over points and regions; no history pool of fakes and no identity loss (the
domains have different channel counts). Adam for the generators together and for the
discriminators together, constant learning rates.

Determinism: torch seeded once before the networks are built, deterministic algorithms,
``threads`` CPU threads; step s draws its batch from numpy's generator seeded with
(seed, s), so nothing random is carried between steps and a resumed run repeats an
uninterrupted one exactly: same seed, data and threads give the same bytes.

Files in ``out_dir`` (each written atomically):

- config.json   the run's config (TrainConfig, classes, dataset, data checksums, versions)
- losses.csv    one row per step, columns LOSS_COLUMNS (below), rewritten at each checkpoint
- checkpoint.pt every ``checkpoint_every`` steps and at the end: the full training state
- intensity.pt  at the end: the rgb -> int generator and the config (estimator.py reads it)
"""

import csv
import hashlib
import io
import json
import platform
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..classes import DATASETS
from ..errors import InputError
from ..files import atomic_output, output_path
from ..learning import load_checkpoint, save_checkpoint
from ..progress import progress_bar
from . import losses, model

OUTPUT_FILES = ("config.json", "losses.csv", "checkpoint.pt", "intensity.pt")  # module docstring

TRAINING_FORMAT = "pgt_blender.intensity_training/1"
LOSS_COLUMNS = (
    "step",               # 1-based step the row's losses were computed in (before its update)
    "generator",          # L_G, the generators' total
    "gan_int",            # (D_int(G(rgb)) - 1)^2
    "gan_rgb",            # (D_rgb(F(int)) - 1)^2
    "cycle_rgb",          # |F(G(rgb)) - rgb|_1, before lambda_cycle
    "cycle_int",          # |G(F(int)) - int|_1, before lambda_cycle
    "group",              # the group intensity loss, lambda_group included
    "discriminator_int",  # D_int's LSGAN loss
    "discriminator_rgb",  # D_rgb's LSGAN loss
)


@dataclass
class TrainConfig:
    """Training settings; the paper's where it gives them (points, lambda_group)."""

    points: int = 256              # P per object (paper: 256, farthest point sampled)
    patches: int = losses.PATCHES  # N ball patches of the group loss
    patch_radius: float = losses.PATCH_RADIUS  # normalised box frame
    lambda_group: float = losses.GROUP_WEIGHT  # paper: 0.1
    lambda_cycle: float = 10.0     # CycleGAN's default
    lr_generator: float = 1e-3
    lr_discriminator: float = 1e-3
    beta1: float = 0.5             # Adam betas as CycleGAN's (0.5, 0.999)
    beta2: float = 0.999
    batch: int = 8
    steps: int = 1000             # about a minute on 2 cores
    checkpoint_every: int = 100
    seed: int = 0
    threads: int = 2               # torch CPU threads: part of what makes the bytes repeat

    def check(self) -> None:
        """ValueError naming the first setting out of range."""
        if min(self.batch, self.steps, self.checkpoint_every, self.patches, self.threads) < 1:
            raise ValueError("batch, steps, checkpoint_every, patches and threads must be positive")
        if self.points < model.SA1[0] or self.patches > self.points:
            raise ValueError(f"points ({self.points}) must be at least {model.SA1[0]} and patches at most points")


def _check_set(objects, channels: int, role: str) -> None:
    """InputError for an ObjectSet whose arrays disagree or hold bad numbers."""
    count = len(objects.names)
    if objects.xyz.ndim != 3 or objects.xyz.shape[0] != count or objects.xyz.shape[2] != 3:
        raise InputError(f"{role} objects", f"xyz has shape {objects.xyz.shape}, expected ({count}, P, 3)")
    if objects.values.shape != (*objects.xyz.shape[:2], channels):
        raise InputError(f"{role} objects", f"values have shape {objects.values.shape}, expected "
                                            f"{(*objects.xyz.shape[:2], channels)} ({channels} columns per point)")
    if objects.class_index.shape != (count,) or not np.isin(objects.class_index, range(len(objects.classes))).all():
        raise InputError(f"{role} objects", f"class_index must be {count} indices into {len(objects.classes)} classes")
    for name, xyz, values in zip(objects.names, objects.xyz, objects.values):
        if not np.isfinite(xyz).all():
            raise InputError(name, "point coordinates are NaN or infinite")
        bad = int((~np.isfinite(values)).any(axis=1).sum())
        if bad:
            raise InputError(name, f"{role} values are NaN or infinite at {bad} of {len(values)} points")
        if values.min() < 0 or values.max() > 1:
            raise InputError(name, f"{role} values span {values.min():g}..{values.max():g}, outside 0..1 "
                                   "(intensities must be divided by the dataset's maximum)")


def check_sets(real, rgb, config: TrainConfig) -> None:
    """InputError unless ``real`` (K = 1) and ``rgb`` (K = 3) ObjectSets fit each other
    and ``config``: P points each, the same classes, a real object for every rgb class."""
    _check_set(real, 1, "real")
    _check_set(rgb, 3, "rgb")
    for role, objects in (("real", real), ("rgb", rgb)):
        if not len(objects.names):
            raise InputError(f"{role} objects", "none to train on")
        if objects.xyz.shape[1] != config.points:
            raise InputError(f"{role} objects", f"{objects.xyz.shape[1]} points each, the config says {config.points}")
    if tuple(real.classes) != tuple(rgb.classes):
        raise InputError("rgb objects", f"classes {tuple(rgb.classes)} differ from the real objects' "
                                        f"{tuple(real.classes)}")
    if real.dataset not in DATASETS:
        raise InputError("real objects", f"unknown dataset '{real.dataset}' ({', '.join(DATASETS)})")
    unpaired = sorted(set(rgb.class_index.tolist()) - set(real.class_index.tolist()))
    if unpaired:
        raise InputError("real objects", "no real object of class " + ", ".join(real.classes[i] for i in unpaired))


def _checksum(objects) -> dict:
    digest = hashlib.sha256()
    for array in (objects.xyz, objects.values, objects.class_index):
        digest.update(np.ascontiguousarray(array).tobytes())
    return {"objects": len(objects.names), "sha256": digest.hexdigest()}


def run_config(real, rgb, config: TrainConfig, torch) -> dict:
    """What config.json and the checkpoints record (JSON types only)."""
    return json.loads(json.dumps({
        "format": model.FORMAT, "architecture": model.ARCHITECTURE, **asdict(config),
        "classes": list(real.classes), "dataset": real.dataset,
        "data": {"real": _checksum(real), "rgb": _checksum(rgb)},
        "losses": "LSGAN + lambda_cycle L1 cycle + group intensity (Hungarian on L1 centre distance)",
        "versions": {"torch": str(torch.__version__), "numpy": np.__version__, "python": platform.python_version()},
    }))


class _Domain:
    """One ObjectSet's fixed per-object geometry: backbone neighbourhoods and the group
    loss's patches (centres (B, N, 3), masks (B, N, P) float32)."""

    def __init__(self, objects, config: TrainConfig):
        self.values = np.asarray(objects.values, np.float32)
        self.class_index = np.asarray(objects.class_index, np.int64)  # what nn.Embedding takes
        self.links = model.neighbourhoods(objects.xyz, with_points=True)
        centres = losses.farthest_point_centres(objects.xyz, config.patches)
        self.centres = np.take_along_axis(objects.xyz, centres[..., None], axis=1)
        self.masks = losses.ball_patches(objects.xyz, centres, config.patch_radius).astype(np.float32)

    def batch(self, torch, rows: np.ndarray) -> tuple:
        """(links tensors, support query tensors, values (B, P, K), class_index (B,))."""
        links = {key: value[rows] for key, value in self.links.items()}
        query = model.support_queries(links)
        return (model.as_tensors(torch, links), model.as_tensors(torch, query),
                torch.from_numpy(self.values[rows]), torch.from_numpy(self.class_index[rows]))


def draw_pairs(real, rgb, batch: int, seed: int, step: int) -> tuple:
    """(rgb rows (batch,), real rows (batch,)) of step ``step``: rgb objects uniformly,
    each with a uniformly drawn real object of its class."""
    rng = np.random.default_rng([seed, step])
    rgb_rows = rng.integers(len(rgb.names), size=batch)
    real_rows = np.array([rng.choice(np.flatnonzero(real.class_index == rgb.class_index[row])) for row in rgb_rows])
    return rgb_rows, real_rows


class _Networks:
    """The four networks and their two optimisers."""

    def __init__(self, torch, classes: int, config: TrainConfig):
        self.g = model.generator(classes, 3, 1)    # rgb -> int
        self.f = model.generator(classes, 1, 3)    # int -> rgb
        self.d_int = model.discriminator(classes, 1)
        self.d_rgb = model.discriminator(classes, 3)
        betas = (config.beta1, config.beta2)
        self.opt_g = torch.optim.Adam([*self.g.parameters(), *self.f.parameters()], config.lr_generator, betas)
        self.opt_d = torch.optim.Adam([*self.d_int.parameters(), *self.d_rgb.parameters()],
                                      config.lr_discriminator, betas)

    def state(self) -> dict:
        return {"networks": {name: getattr(self, name).state_dict() for name in ("g", "f", "d_int", "d_rgb")},
                "optimisers": {"g": self.opt_g.state_dict(), "d": self.opt_d.state_dict()}}

    def load(self, state: dict) -> None:
        for name, weights in state["networks"].items():
            getattr(self, name).load_state_dict(weights)
        self.opt_g.load_state_dict(state["optimisers"]["g"])
        self.opt_d.load_state_dict(state["optimisers"]["d"])


def train_step(torch, nets: _Networks, rgb: _Domain, real: _Domain, rgb_rows, real_rows,
               config: TrainConfig) -> dict:
    """One generator and one discriminator update on a batch of pairs; the losses
    (LOSS_COLUMNS but step) as floats, computed before the updates."""
    links_a, query_a, a, class_a = rgb.batch(torch, rgb_rows)
    links_b, query_b, b, class_b = real.batch(torch, real_rows)
    shape_a, shape_b = a.shape[:2], b.shape[:2]

    def run(net, links, query, values, classes, shape):
        return net(links, values, classes, {**query, "values": values.reshape(-1, values.shape[-1])}).view(*shape, -1)

    for d in (nets.d_int, nets.d_rgb):
        d.requires_grad_(False)  # the generator step leaves the discriminators alone
    fake_int = run(nets.g, links_a, query_a, a, class_a, shape_a)
    fake_rgb = run(nets.f, links_b, query_b, b, class_b, shape_b)
    rec_rgb = run(nets.f, links_a, query_a, fake_int, class_a, shape_a)
    rec_int = run(nets.g, links_b, query_b, fake_rgb, class_b, shape_b)
    _, cols = zip(*(losses.match_patches(rgb.centres[i], real.centres[j]) for i, j in zip(rgb_rows, real_rows)))
    fake_means = losses.patch_means(torch.from_numpy(rgb.masks[rgb_rows]), fake_int[..., 0])
    real_means = losses.patch_means(torch.from_numpy(real.masks[real_rows]), b[..., 0])
    out = {
        "gan_int": ((nets.d_int(links_a, fake_int, class_a) - 1) ** 2).mean(),
        "gan_rgb": ((nets.d_rgb(links_b, fake_rgb, class_b) - 1) ** 2).mean(),
        "cycle_rgb": (rec_rgb - a).abs().mean(),
        "cycle_int": (rec_int - b).abs().mean(),
        "group": losses.matched_patch_loss(fake_means, real_means, torch.from_numpy(np.stack(cols)),
                                           config.lambda_group),
    }
    out["generator"] = (out["gan_int"] + out["gan_rgb"] + config.lambda_cycle * (out["cycle_rgb"] + out["cycle_int"])
                        + out["group"])
    nets.opt_g.zero_grad()
    out["generator"].backward()
    nets.opt_g.step()

    for d in (nets.d_int, nets.d_rgb):
        d.requires_grad_(True)
    out["discriminator_int"] = (((nets.d_int(links_b, b, class_b) - 1) ** 2).mean()
                                + (nets.d_int(links_a, fake_int.detach(), class_a) ** 2).mean()) / 2
    out["discriminator_rgb"] = (((nets.d_rgb(links_a, a, class_a) - 1) ** 2).mean()
                                + (nets.d_rgb(links_b, fake_rgb.detach(), class_b) ** 2).mean()) / 2
    nets.opt_d.zero_grad()
    (out["discriminator_int"] + out["discriminator_rgb"]).backward()
    nets.opt_d.step()
    return {key: float(value.detach()) for key, value in out.items()}


def _write_text(path: Path, text: str) -> None:
    with atomic_output(path) as stream:
        stream.write(text.encode())


def _csv_text(rows: list) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(LOSS_COLUMNS)
    writer.writerows(rows)
    return buffer.getvalue()


def _resume_state(torch, out_dir: Path, config: dict) -> tuple:
    """(training state dict, loss rows up to its step) of out_dir's checkpoint; InputError
    when it is unreadable or damaged, from a different run (any setting but ``steps``
    differs, named before the training objects and versions, which follow from the
    settings) or past the ``steps`` asked for."""
    path = out_dir / "checkpoint.pt"
    state = load_checkpoint(torch, path, TRAINING_FORMAT, "intensity training", "train without --resume")
    saved, step = state.get("config"), state.get("step")
    if not isinstance(saved, dict) or isinstance(step, bool) or not isinstance(step, int) or step < 0 \
            or not isinstance(state.get("networks"), dict) or not isinstance(state.get("optimisers"), dict):
        raise InputError(path, "damaged (its settings, step, networks or optimisers are missing or not what "
                               "training writes); train without --resume")
    if step > config["steps"]:
        raise InputError(path, f"is at step {step}, past the {config['steps']} steps asked for")
    changed = [key for key in set(saved) | set(config) if key != "steps" and saved.get(key) != config.get(key)]
    if changed:
        key = min(changed, key=lambda key: (key in ("data", "versions"), key))  # a setting before what follows
        what = ("the training objects differ" if key == "data"
                else f"{key}: {saved.get(key)!r} there, {config.get(key)!r} now")
        raise InputError(path, f"was written by a different run ({what}); train without --resume or use another "
                               f"folder")
    return state, _loss_rows(out_dir / "losses.csv", state["step"])


def _loss_rows(path: Path, step: int) -> list:
    """The rows of losses.csv up to ``step`` (none when the file is missing); InputError
    when it is not the table this module writes."""
    if not path.is_file():
        return []
    try:
        with open(path, newline="", encoding="utf-8") as stream:
            table = list(csv.reader(stream))
        if not table or tuple(table[0]) != LOSS_COLUMNS:
            raise ValueError(f"the header is not {','.join(LOSS_COLUMNS)}")
        for number, row in enumerate(table[1:], 2):
            if len(row) != len(LOSS_COLUMNS):
                raise ValueError(f"line {number} has {len(row)} values, not {len(LOSS_COLUMNS)}")
            int(row[0]), [float(value) for value in row[1:]]
    except (UnicodeDecodeError, ValueError, csv.Error) as error:
        raise InputError(path, f"damaged ({error}); delete it to resume without the earlier loss rows, or train "
                               f"without --resume") from None
    return [row for row in table[1:] if int(row[0]) <= step]


def train(real, rgb, config: TrainConfig, out_dir, resume: bool = False, progress: bool = True) -> Path:
    """Train on ObjectSets ``real`` (K = 1) and ``rgb`` (K = 3) and return the path of
    the final checkpoint, ``out_dir``/intensity.pt. With ``resume`` and a checkpoint.pt
    in ``out_dir`` (same run, ``steps`` may be raised) training goes on from its step;
    without one it starts at step 0. InputError for bad sets or a foreign checkpoint."""
    out_dir = Path(out_dir)
    for name in OUTPUT_FILES:  # a folder in the way is found before the training, not after it
        output_path(out_dir / name)
    torch = model.require_torch(out_dir)
    config.check()
    check_sets(real, rgb, config)
    record = run_config(real, rgb, config, torch)
    out_dir.mkdir(parents=True, exist_ok=True)
    state, rows = (None, [])
    if resume and (out_dir / "checkpoint.pt").is_file():
        state, rows = _resume_state(torch, out_dir, record)
    rgb_domain, real_domain = _Domain(rgb, config), _Domain(real, config)

    previous = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(config.threads)
    torch.use_deterministic_algorithms(True)
    try:
        with torch.random.fork_rng(devices=[]):  # leave the caller's torch RNG alone
            torch.manual_seed(config.seed)
            nets = _Networks(torch, len(real.classes), config)
        start = 0
        if state is not None:
            try:
                nets.load(state)
            except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as error:  # torch's load_state_dict
                raise InputError(out_dir / "checkpoint.pt", f"damaged ({type(error).__name__}: {error}); train "
                                                            f"without --resume") from None
            start = state["step"]
        # written once a resume is accepted: a refused one leaves the folder as it was
        _write_text(out_dir / "config.json", json.dumps(record, indent=2, sort_keys=True) + "\n")
        with progress_bar(progress, config.steps, "step", initial=start) as bar:
            for step in range(start + 1, config.steps + 1):
                rgb_rows, real_rows = draw_pairs(real, rgb, config.batch, config.seed, step)
                values = train_step(torch, nets, rgb_domain, real_domain, rgb_rows, real_rows, config)
                rows.append([step, *(f"{values[key]:.6g}" for key in LOSS_COLUMNS[1:])])
                if bar is not None:
                    bar.update()
                    bar.set_postfix(generator=rows[-1][1], group=rows[-1][6], refresh=False)
                if step % config.checkpoint_every == 0 or step == config.steps:
                    _write_text(out_dir / "losses.csv", _csv_text(rows))
                    save_checkpoint(torch, out_dir / "checkpoint.pt",
                                    {"format": TRAINING_FORMAT, "config": record, "step": step, **nets.state()})
    finally:
        torch.set_num_threads(previous[0])
        torch.use_deterministic_algorithms(previous[1])
    final = out_dir / "intensity.pt"
    save_checkpoint(torch, final, {"format": model.FORMAT, "config": record, "state_dict": nets.g.state_dict()})
    return final
