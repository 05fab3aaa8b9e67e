"""clothgap: the command line and the plumbing the four stages share.

The stages themselves live in the top-level packages ``sim``, ``render``,
``learn`` and ``eval``; this package holds only what they have in common: the
study config and its presets, run folders with per-clip done markers, and the
per-stage, per-clip seeds.
"""

__version__ = "0.1.0"
