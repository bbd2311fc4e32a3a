"""PyTorch for the learned steps (heading classifier, intensity estimator), imported
only inside the functions that need it, so the rest of the core works without it."""

from .errors import InputError

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
