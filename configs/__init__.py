"""Configs that ship with torchconn, installed as the package ``torchconn.configs``.

The paper's sweep configs (``default``, ``quick``, ``fig3``, ``fig4a``, ``fig4b``), the
discrepancy power study's ``discrepancy_power`` and the optimised gaits ``gaits.toml``. The
folder stays at the repository's top level; ``pyproject.toml`` maps it into the package, and
:mod:`torchconn._resources` reads it with :mod:`importlib.resources`.
"""
