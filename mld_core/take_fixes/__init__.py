"""What a sampled take is made to meet before it is handed out: the take fixes, each a small object with its own
config, applied in one declared order (``order.py``):

1. ``stepping.py``: a Final take's latent refined until its feet step instead of slide (config ``stepping``);
2. ``meet_constraints.py``: the latent and then the features refined until the constraints (``constraints.py``:
   poses to hit, a root path, a loop) are met;
3. ``repair.py``: one skeleton and planted, locked feet for a free take's features (config ``repair``);
4. ``side_redraw.py``: a free take that misses the side its prompt names drawn again (config ``side_redraws``);
5. ``verb_redraw.py``: a free take that does not show the checked verbs its prompt names drawn again (config
   ``verb_redraws``). Both share the loop of ``redraw.py``.

A new fix: a module here with its config (a field of the model config, saved in config.json) and a class with
``apply(takes, decoder) -> Takes`` and ``timings``, placed in ``order.fixes_for``.
"""
