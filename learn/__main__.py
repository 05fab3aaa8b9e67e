"""``python -m learn RUN_DIR [...]`` and ``torchrun ... -m learn RUN_DIR``: see ``learn.stage.main``."""

from learn.stage import main

main()
