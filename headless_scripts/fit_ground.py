"""Shim of pgt_blender.commands.fit_ground (its docstring is the help), so that
``blender -b -P headless_scripts/fit_ground.py -- ARGS`` and ``python headless_scripts/fit_ground.py ARGS`` run it."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "addon"))
from pgt_blender.cli import launch  # noqa: E402

launch("fit_ground")
