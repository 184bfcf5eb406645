"""What the add-on does to a Blender scene (bpy, main thread): read a rig, key takes onto it as Actions, build the
canonical armature, render a preview."""
