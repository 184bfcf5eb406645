"""What a sampled take is made to meet before it is handed out.

- ``stepping.py``: the cost that makes a take's feet step instead of slide (config ``stepping``).
- ``constraints.py``: poses to hit, a root path, a loop, as costs on the joints.
- ``repair.py``: one skeleton and planted, locked feet for a free take's features (config ``repair``).
"""
