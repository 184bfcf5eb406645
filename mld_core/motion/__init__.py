"""Motion representation: BVH files, the canonical 22-joint skeleton, HumanML3D's 263-d features."""
