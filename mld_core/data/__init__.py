"""Training data: preparing folders (Bandai) and loading any HumanML3D-format folder."""
