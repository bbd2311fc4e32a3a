"""Progress bars of long core steps: tqdm when asked for and installed (headless runs),
nothing otherwise (Blender's Python may lack tqdm; the panels show their own progress)."""


def progress_bar(enabled: bool, total: int | None, unit: str, initial: int = 0, leave: bool = True):
    """A tqdm bar of ``total`` ``unit`` starting at ``initial``, or None."""
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm(total=total, initial=initial, unit=unit, mininterval=1.0, leave=leave)
