"""The Blender user interface (bpy, main thread): operators, panels, properties, preferences, the Retarget and
quality sub-panels, and the timer that hands finished jobs to the scene."""
