"""What a prompt becomes before the denoiser reads it.

- ``coverage.py``: how close a prompt is to the training captions (a score, a verdict, the nearest captions).
- ``content_anchor.py``: a prompt's sentence vector moved towards the content a linear classifier reads in it.
- ``side_contrast.py``: the sentence vector of a prompt that names a side pushed away from its mirrored wording's.
"""
