"""Installed as ``mmcv/_ext.py`` in .venv-mmdet3d: mmcv-lite ships no compiled ops, and
``mmcv.ops`` (imported by mmdet3d.structures) asks the extension module for each op by
name. Every op here raises when called; the ground-truth sampler calls none."""


def __getattr__(name):
    def unavailable(*args, **kwargs):
        raise NotImplementedError(f"mmcv op {name} is compiled, and mmcv-lite has none")

    return unavailable
