"""What a prompt becomes before the denoiser reads it.

- ``text.py``: a prompt's text condition: the text encoder's embedding, each prompt encoded once per encoder and kept,
  its sentence vector moved by the tricks below, in order;
- ``content_anchor.py``: the sentence vector moved towards the content a linear classifier reads in it;
- ``side_contrast.py``: the sentence vector of a prompt that names a side pushed away from its mirrored wording's;
- ``coverage.py``: how close a prompt is to the training captions (a score, a verdict, the nearest captions; the
  anchor's ramp reads it).
"""
