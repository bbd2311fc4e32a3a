"""Shim of pgt_blender.commands.place_objects (its docstring is the help), so that
``blender -b -P headless_scripts/place_objects.py -- ARGS`` and ``python headless_scripts/place_objects.py ARGS`` run it."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "addon"))
from pgt_blender.cli import launch  # noqa: E402

launch("place_objects")
