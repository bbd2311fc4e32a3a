"""Every panel, menu and preferences draw of the add-on, run in realistic scene states.

Background Blender never draws, so the draw code runs here through ``Recorder``, a
stand-in for ``UILayout`` that checks each call against the real RNA of the running
Blender: layout functions and their keyword arguments, property names on their data,
operator idnames and the operator properties set, and icon names. A mistake raises
``DrawError`` naming it; ``test_the_recorder_catches_mistakes`` keeps the checker honest.
"""

from types import SimpleNamespace

import os
import re
from pathlib import Path

import pytest

from pgt_blender.core.samples import write_sample

bpy = pytest.importorskip("bpy")

from pgt_blender.blender import objects, properties, ui  # noqa: E402  (needs bpy)
from pgt_blender.core.importing import load_reconstruction  # noqa: E402


class DrawError(AssertionError):
    """A draw call that real Blender would refuse or show wrongly."""


LAYOUT = bpy.types.UILayout.bl_rna
ICONS = set(LAYOUT.functions["label"].parameters["icon"].enum_items.keys())


class OperatorRecorder:
    """What ``layout.operator`` returns: operator properties set on it must exist."""

    def __init__(self, idname: str, rna):
        object.__setattr__(self, "idname", idname)
        object.__setattr__(self, "rna", rna)

    def __setattr__(self, name, value):
        if name not in self.rna.properties.keys():
            raise DrawError(f"operator {self.idname} has no property '{name}'")


class Recorder:
    """A ``UILayout`` that records its calls and checks them against real RNA."""

    def __init__(self, calls: list):
        object.__setattr__(self, "calls", calls)

    def __setattr__(self, name, value):  # enabled, alert, active, scale_y ...
        if name not in LAYOUT.properties.keys():
            raise DrawError(f"UILayout has no attribute '{name}'")

    def __getattr__(self, name):
        if name not in LAYOUT.functions.keys():
            raise DrawError(f"UILayout has no function '{name}'")
        parameters = LAYOUT.functions[name].parameters

        def call(*args, **kwargs):
            names = [p.identifier for p in parameters if not p.is_output]
            for key in list(kwargs) + names[:len(args)]:
                if key not in names:
                    raise DrawError(f"UILayout.{name}() has no argument '{key}'")
            if kwargs.get("icon", "NONE") not in ICONS:
                raise DrawError(f"unknown icon '{kwargs['icon']}' in UILayout.{name}()")
            arguments = dict(zip(names, args), **kwargs)
            self.calls.append((name, arguments))
            result = _check_prop(**arguments) if name == "prop" else (
                _check_operator(**arguments) if name == "operator" else None)
            returns = [p for p in parameters if p.is_output]
            if returns and returns[0].fixed_type == LAYOUT:
                return Recorder(self.calls)
            return result

        return call


def _check_prop(data, property, **_):
    if property not in data.bl_rna.properties.keys():
        raise DrawError(f"{data.bl_rna.identifier} has no property '{property}'")


def _check_operator(operator, **_):
    category, _, name = operator.partition(".")
    try:
        rna = getattr(getattr(bpy.ops, category), name).get_rna_type()
    except (AttributeError, KeyError):
        raise DrawError(f"no operator '{operator}'") from None
    return OperatorRecorder(operator, rna)


def draw_each(context) -> dict:
    """{title: calls} of each panel whose poll passes, the import menu entries and the
    preferences, each drawn into its own recorder."""
    drawn = {}
    for panel in ui.classes:
        if not hasattr(panel, "poll") or panel.poll(context):
            panel.draw(SimpleNamespace(layout=Recorder(drawn.setdefault(f"PGT > {panel.bl_label}", []))), context)
    ui.menu_import(SimpleNamespace(layout=Recorder(drawn.setdefault("File > Import", []))), context)
    stand_in = SimpleNamespace(layout=Recorder(drawn.setdefault("Preferences > Add-ons > PGT Blender", [])),
                               bl_rna=properties.PGTPreferences.bl_rna, intensity_checkpoint="")
    properties.PGTPreferences.draw(stand_in, context)
    return drawn


def draw_everything(context) -> list:
    """Every call of ``draw_each`` in one list."""
    return [call for calls in draw_each(context).values() for call in calls]


def _add(scene, path):
    obj = objects.add_reconstruction(scene, load_reconstruction(path))
    for other in bpy.context.selected_objects:
        other.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    return obj


@pytest.fixture(scope="module")
def samples(tmp_path_factory):
    folder = tmp_path_factory.mktemp("samples")
    return [write_sample(folder, name, seed=1, points=1500)["reconstruction.ply"] for name in ("truck", "bus", "bicycle")]


def _state(scene, samples, name):
    """Bring the empty scene into the state ``name``."""
    if name == "empty":
        return
    if name.startswith("bank"):
        settings = scene.pgt_bank
        settings.status = "exporting 48 entries" if name == "bank running" else "48 entries written"
        settings.running, settings.progress = name == "bank running", 0.4
        settings.config_file = "//bank.toml" if name == "bank config file" else ""
        return
    obj = _add(scene, samples[0])
    settings = scene.pgt_authoring
    if name == "imported":
        return
    if name == "unknown kind":  # a .blend of a version with another source kind: its index reads ""
        obj.pgt["source_kind"] = 99
        return
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    if name == "aligned":
        return
    if name == "class cleared":
        settings.class_name, settings.dataset = "bus", "kitti"
        return
    if name == "exact size":
        settings.size_mode = "exact"
        return
    settings.dataset, settings.class_name = "nuscenes", "truck"
    for mode in ("exact", "keep", "class"):  # each mode's fields drawn below in "sized"
        settings.size_mode = mode
    assert bpy.ops.object.pgt_set_size() == {"FINISHED"}
    if name == "sized":
        return
    scene.pgt_scan.sensor = "CUSTOM" if name == "custom sensor" else "nuscenes"
    if name == "custom sensor":
        return
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    if name == "scanned":
        return
    if name == "deleted source":  # the scan preview stays active, its object gone
        preview = bpy.data.objects[f"{obj.name} Scan"]
        bpy.data.objects.remove(obj)
        bpy.context.view_layer.objects.active = preview
    elif name == "edit mode":
        bpy.context.view_layer.objects.active = obj
        bpy.ops.object.mode_set(mode="EDIT")
    elif name == "many objects":
        for path in samples[1:] * 4:
            _add(scene, path)


STATES = ["empty", "imported", "aligned", "class cleared", "exact size", "sized", "custom sensor", "scanned",
          "deleted source", "edit mode", "many objects", "bank running", "bank config file", "unknown kind"]


@pytest.mark.parametrize("state", STATES)
def test_every_panel_draws_with_valid_references(scene, samples, state):
    _state(scene, samples, state)
    calls = draw_everything(bpy.context)
    drawn = {arguments.get("property") for name, arguments in calls if name == "prop"}
    assert {"sensor", "distance", "color_by", "intensity_checkpoint"} <= drawn
    if state not in ("empty", "deleted source", "bank running", "bank config file", "unknown kind"):
        assert {"up", "heading_method", "size_mode"} <= drawn  # the authoring panels polled in
    if bpy.context.mode == "EDIT_MESH":
        bpy.ops.object.mode_set(mode="OBJECT")


@pytest.mark.parametrize("mistake, message", [
    (lambda layout, scene: layout.prop(scene.pgt_scan, "sensr"), "PGT_PG_scan has no property 'sensr'"),
    (lambda layout, scene: layout.operator("object.pgt_scna"), "no operator 'object.pgt_scna'"),
    (lambda layout, scene: setattr(layout.operator("object.pgt_turn"), "turn", 2),
     "operator object.pgt_turn has no property 'turn'"),
    (lambda layout, scene: layout.label(text="x", icon="NOT_AN_ICON"), "unknown icon 'NOT_AN_ICON'"),
    (lambda layout, scene: layout.prop(scene.pgt_scan, "sensor", expnad=True), "has no argument 'expnad'"),
    (lambda layout, scene: layout.colum(), "UILayout has no function 'colum'"),
    (lambda layout, scene: setattr(layout.row(), "enabeld", False), "UILayout has no attribute 'enabeld'"),
])
def test_the_recorder_catches_mistakes(scene, mistake, message):
    with pytest.raises(DrawError, match=message):
        mistake(Recorder([]), scene)


# --- the user guide's panel reference, generated from the RNA --------------------------

GUIDE = Path(__file__).resolve().parents[1] / "docs" / "user_guide.md"
BEGIN = "<!-- panel reference: generated by tests/test_blender_draw.py; PGT_WRITE_DOCS=1 rewrites it -->"
END = "<!-- end of panel reference -->"


def _row(label: str, tooltip: str) -> str:
    return f"| {label} | {' '.join(tooltip.split()).replace('|', '/')} |"


def panel_reference() -> str:
    """Markdown: per panel, each field and button it can show (drawn in every state of
    STATES) with Blender's label and tooltip from the RNA."""
    seen, labels = {}, {}
    for state in STATES:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        _state(bpy.context.scene, _reference_samples(), state)
        for title, calls in draw_each(bpy.context).items():
            rows = seen.setdefault(title, {})
            for name, arguments in calls:
                if name == "prop":
                    prop = arguments["data"].bl_rna.properties[arguments["property"]]
                    rows.setdefault(("prop", prop.identifier), _row(prop.name, prop.description))
                elif name == "operator":
                    category, _, op = arguments["operator"].partition(".")
                    rna = getattr(getattr(bpy.ops, category), op).get_rna_type()
                    shown = labels.setdefault((title, rna.identifier), [])  # as drawn: one operator, several buttons
                    if (arguments.get("text") or rna.name) not in shown:
                        shown.append(arguments.get("text") or rna.name)
                    rows[("op", rna.identifier)] = _row(f"{', '.join(f'*{label}*' for label in shown)} "
                                                        f"({'button' if len(shown) == 1 else 'buttons'})",
                                                        rna.description)
        if bpy.context.mode == "EDIT_MESH":
            bpy.ops.object.mode_set(mode="OBJECT")
    order = [f"PGT > {panel.bl_label}" for panel in ui.classes] + ["File > Import", "Preferences > Add-ons > PGT Blender"]
    blocks = []
    for title in order:
        panel = next((p for p in ui.classes if f"PGT > {p.bl_label}" == title), None)
        if not seen[title]:  # a list, no fields: say what it shows
            blocks.append(f"**{title}**: {' '.join(panel.__doc__.split())}")
            continue
        blocks.append(f"**{title}**\n\n| Field | What it does |\n|---|---|\n" + "\n".join(seen[title].values()))
    return "\n\n".join([BEGIN, *blocks, END])


_SAMPLES = []


def _reference_samples():
    if not _SAMPLES:
        import tempfile

        folder = Path(tempfile.mkdtemp(prefix="pgt_reference_"))
        _SAMPLES.extend(write_sample(folder, name, seed=1, points=1500)["reconstruction.ply"]
                        for name in ("truck", "bus", "bicycle"))
    return _SAMPLES


def test_user_guide_panel_reference_matches_the_rna(registered):
    text = GUIDE.read_text()
    reference = panel_reference()
    if os.environ.get("PGT_WRITE_DOCS"):
        text = re.sub(re.escape(BEGIN) + ".*?" + re.escape(END), lambda _: reference, text, flags=re.S)
        GUIDE.write_text(text)
    assert reference in text, ("docs/user_guide.md's panel reference differs from the panels: "
                               "PGT_WRITE_DOCS=1 .venv/bin/python -m pytest tests/test_blender_draw.py -k reference")
