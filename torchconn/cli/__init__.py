"""The scaffold every command shares (``fit``, ``convert``, ``discrepancy``, ``improve``,
``sweep``): :mod:`.common` (the flags every command takes, config files and ``--set``
overrides) and :mod:`.conversion` (the tracking-file options and reading of recordings).

The plumbing beneath (errors, threads, devices, output folders) is :mod:`torchconn._cli`.
"""
