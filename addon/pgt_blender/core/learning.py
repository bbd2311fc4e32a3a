"""PyTorch for the learned steps (heading classifier, intensity estimator), imported
only inside the functions that need it, so the rest of the core works without it; and
their checkpoint files, one format for all.

Checkpoint: a ``torch.save`` archive of a dict whose ``"format"`` names what it holds
(``"pgt_blender.<kind>/<version>"``) beside tensors and plain data; written atomically
and byte for byte the same for the same contents, read with ``weights_only`` (no code
runs), a wrong or damaged file being an InputError naming it.
"""

import io
import pickle
import sys
from pathlib import Path

from .errors import InputError
from .files import atomic_output

TORCH_REQUIREMENT = "torch==2.13.0"


def require_torch(path, what: str):
    """The torch module; InputError(path) with a one-line reason when this Python cannot
    import it. ``path``: the checkpoint or output the caller was about to use; ``what``
    needs it, e.g. "the heading classifier"."""
    try:
        import torch
    except ImportError:
        raise InputError(path, f"{what} needs PyTorch ({TORCH_REQUIREMENT}), which this Python cannot import") from None
    return torch


def save_checkpoint(torch, path, payload: dict) -> None:
    """Write ``payload`` (with its ``"format"``) to ``path`` with the ``torch`` module
    (require_torch). The archive is built in memory first: torch names its inner folder
    after the file it writes, which would put a temporary file's name into the bytes."""
    buffer = io.BytesIO()
    torch.save(_canonical(payload), buffer)
    with atomic_output(path) as stream:
        stream.write(buffer.getvalue())


def load_checkpoint(torch, path, format_tag: str, kind: str, missing: str, build=None):
    """``build(payload)`` (default: the payload dict) of the ``kind`` checkpoint at
    ``path``, read with the ``torch`` module (require_torch). InputError when the file is
    missing (``missing`` says how to make one), damaged, of another format, or ``build``
    fails on it (a state dict that does not fit the network)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, f"no {kind} checkpoint here ({missing})")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
        found = payload.get("format") if isinstance(payload, dict) else None
        if found != format_tag:
            raise ValueError(f"format {found!r}, expected {format_tag!r}")
        return payload if build is None else build(payload)
    except Exception as error:  # torch raises many types for a damaged archive
        if isinstance(error, pickle.UnpicklingError):  # torch's text would advise the unsafe load
            raise InputError(path, f"not a readable {kind} checkpoint (not a torch file of tensors and plain "
                                   f"values, the only kind read)") from None
        reason = str(error).split("\n")[0][:200]  # torch's messages run to paragraphs
        raise InputError(path, f"not a readable {kind} checkpoint ({type(error).__name__}: {reason})") from None


MAX_CLOUD_POINTS = 16384  # points per cloud a network sees: beyond, GBs per batch


# checked_config's check of a checkpoint's points per cloud
CLOUD_POINTS_FIELD = (lambda value: isinstance(value, int) and not isinstance(value, bool)
                      and 1 <= value <= MAX_CLOUD_POINTS, f"a whole number 1 .. {MAX_CLOUD_POINTS}")


def checked_config(saved: dict, checks: dict) -> dict:
    """``saved["config"]`` once every ``checks`` entry (field -> (test, what it must be))
    holds; ValueError naming the first field that does not, which load_checkpoint
    reports as a damaged checkpoint (a build calls this)."""
    config = saved.get("config")
    if not isinstance(config, dict):
        raise ValueError(f"its config is {type(config).__name__}, not a table")
    for field, (test, meaning) in checks.items():
        if not test(config.get(field)):
            raise ValueError(f"its config's {field} is {config.get(field)!r}, not {meaning}")
    return config


def _canonical(value):
    """A copy of nested dicts, lists and tuples with every string interned. Pickle
    writes an object seen before as a reference to it, by identity: a resumed run's
    strings come from a loaded file while a fresh run's are shared literals, so
    without this the same values would pickle to different bytes. numpy strings (class
    names read from info pickles) become plain ones."""
    if isinstance(value, str):
        return sys.intern(str(value))
    if isinstance(value, dict):
        return {_canonical(key): _canonical(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_canonical(item) for item in value)
    return value
