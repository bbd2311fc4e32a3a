"""Chunk records (``OUT/.work/chunks/<chunk>.json``): a chunk's infos, file checksums,
statistics and intensity histograms, in JSON so that reading one cannot run code.

numpy values keep their exact type and bytes: an array or numpy scalar is the object
``{"numpy": <.npy dtype descr>, "shape": [...], "bytes": <base64>}`` (a scalar has
shape ``[]``), so the info pickles assembled from records are the bytes the scan
produced. Only plain numeric, boolean and structured dtypes are read back.
"""

import base64
import json
import sys
from pathlib import Path

import numpy as np

_NUMPY = "numpy"


def write_record(record: dict) -> bytes:
    """``record`` (str keys; lists, str, int, float, bool, numpy arrays and scalars) as JSON bytes."""
    return json.dumps(record, default=_encode, separators=(",", ":")).encode()


def read_record(path: Path):
    """The value stored in ``path``; ValueError (or OSError) when it is not a whole record."""
    return json.loads(Path(path).read_bytes(), object_hook=_decode)


def _encode(value):
    if isinstance(value, (np.ndarray, np.generic)):
        value = np.asarray(value)
        return {_NUMPY: np.lib.format.dtype_to_descr(value.dtype), "shape": list(value.shape),
                "bytes": base64.b64encode(np.ascontiguousarray(value).tobytes()).decode()}
    raise TypeError(f"a chunk record cannot hold {type(value).__name__}")


def _decode(obj: dict):
    if _NUMPY not in obj:
        # one object per distinct string, as when the infos were made: pickle stores a repeat as a reference
        return {sys.intern(key): sys.intern(value) if isinstance(value, str) else value for key, value in obj.items()}
    descr = obj[_NUMPY]
    dtype = np.lib.format.descr_to_dtype([tuple(field) for field in descr] if isinstance(descr, list) else descr)
    if dtype.hasobject or any(dtype[name].kind not in "biuf" for name in dtype.names or ()) \
            or (dtype.names is None and dtype.kind not in "biuf"):
        raise ValueError(f"dtype {dtype} is not allowed in a chunk record")
    array = np.frombuffer(base64.b64decode(obj["bytes"], validate=True), dtype).reshape(obj["shape"]).copy()
    return array[()] if array.ndim == 0 else array
