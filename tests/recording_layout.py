"""A stand-in for Blender's UILayout that records what a panel draws (imported by the bpy test scripts).

Every ``prop`` must name a real property and every ``operator`` a registered operator, so a draw() that refers to
something missing fails the test instead of printing a warning in Blender's console.
"""

import bpy


class Layout:
    calls: list = []

    def __init__(self):
        self.alert = False
        self.enabled = True

    def _sub(self, *a, **k):
        return Layout()

    row = column = box = split = _sub

    def prop(self, data, name, **k):
        assert name in data.bl_rna.properties, name
        Layout.calls.append(("prop", name))

    def prop_search(self, data, name, sdata, sname, **k):
        Layout.calls.append(("prop_search", name, sname))

    def operator(self, idname, **k):
        group, op = idname.split(".")
        assert hasattr(getattr(bpy.ops, group), op), idname
        Layout.calls.append(("operator", idname))
        return OperatorProperties()

    def label(self, text="", **k):
        Layout.calls.append(("label", text))

    def progress(self, factor=0.0, type="BAR", text=""):
        Layout.calls.append(("progress", text))

    def template_list(self, listtype, list_id, data, prop, adata, aprop, **k):
        Layout.calls.append(("template_list", listtype, prop))
        for item in getattr(data, prop):
            getattr(bpy.types, listtype).draw_item(None, bpy.context, Layout(), data, item, 0, adata, aprop)

    def separator(self, **k):
        pass


class OperatorProperties:
    """What ``layout.operator`` returns: the operator's properties, to be set by the panel."""


class Host:
    """What a Panel's draw() gets as ``self``: just a layout."""

    def __init__(self):
        self.layout = Layout()
