"""Progress bars of long core steps: tqdm when asked for and installed (headless runs),
nothing otherwise (Blender's Python may lack tqdm; the panels show their own progress)."""

from contextlib import contextmanager


@contextmanager
def progress_bar(enabled: bool, total: int | None, unit: str, initial: int = 0, leave: bool = True):
    """A tqdm bar of ``total`` ``unit`` starting at ``initial``, or None, for a ``with``
    block that closes it on the way out, also on an error (whose one line would
    otherwise be printed on the bar's line)."""
    tqdm = None
    if enabled:
        try:
            from tqdm import tqdm
        except ImportError:
            pass
    if tqdm is None:
        yield None
        return
    bar = tqdm(total=total, initial=initial, unit=unit, mininterval=1.0, leave=leave)
    try:
        yield bar
    finally:
        bar.close()
