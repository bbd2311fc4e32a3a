"""Pickles read without running code: ground-truth info pickles (``*_dbinfos_*.pkl``,
OpenPCDet's and mmdetection3d's, the bank's and mixes of them). The project's own state
is JSON (bank/records.py), never a pickle.

A plain ``pickle.load`` calls whatever the file names, so a crafted database runs code
on load. ``load_pickle`` allows only what such files hold: Python's containers and
scalars and numpy arrays, dtypes and scalars. Any other global is refused with an
InputError naming the file and the global.
"""

import io
import pickle
from pathlib import Path

from .errors import InputError
from .files import regular_file

_ALLOWED = {
    ("builtins", name) for name in ("dict", "list", "tuple", "set", "frozenset", "str", "bytes", "bytearray",
                                    "int", "float", "complex", "bool", "slice", "range")
} | {("collections", "OrderedDict"), ("numpy", "ndarray"), ("numpy", "dtype"),
     ("_codecs", "encode")} | {  # protocol-2 pickles rebuild an array's bytes with _codecs.encode
    (module, name) for module in ("numpy.core.multiarray", "numpy._core.multiarray")
    for name in ("_reconstruct", "scalar")
}


class _Unpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        if (module, name) not in _ALLOWED:
            raise pickle.UnpicklingError(f"refused to load {module}.{name}: only containers, numbers, strings and "
                                         f"numpy arrays may be in it")
        if module.endswith("multiarray"):  # numpy 2 renamed numpy.core; either pickle loads with either
            try:
                from numpy._core import multiarray
            except ImportError:  # numpy before 1.26
                from numpy.core import multiarray
            return getattr(multiarray, name)
        return super().find_class(module, name)


def load_pickle(path, data: bytes | None = None):
    """The object pickled in ``path`` (or in ``data``, read from ``path``), built only
    from allowed types. InputError "<path>: <problem>" for an unreadable, damaged or
    refused file."""
    path = Path(path) if data is not None else regular_file(path)
    try:
        data = path.read_bytes() if data is None else data
        return _Unpickler(io.BytesIO(data)).load()
    except OSError as error:
        raise InputError(path, f"cannot read the file ({error.strerror or error})") from None
    except Exception as error:  # unpickling damaged bytes raises nearly any exception type
        raise InputError(path, f"not a readable pickle ({type(error).__name__}: {error})") from None
