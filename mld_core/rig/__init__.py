"""Rigs and retargeting without Blender (numpy only): bone maps and their presets, the retarget solve, the
canonical skeleton's exact pose, and turning a pose into the keys to write (resample, reduce, foot lock,
rotation modes). The Blender add-on reads a rig into these arrays and writes the keys it gets back."""
