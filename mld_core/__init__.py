"""mld_core: Motion Latent Diffusion (Chen et al., CVPR 2023) in plain torch + numpy.

Never imports bpy or mathutils. Public surface:

- ``mld_core.pipeline.MLDPipeline`` - ``MLDPipeline.from_pretrained(path)(prompts, seconds=...)``
- ``python -m mld_core ...`` - data preparation, training, generation, evaluation, benchmarks
"""

__version__ = "0.1.0"
