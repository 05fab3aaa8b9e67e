"""``python -m learn RUN_DIR [...]`` and ``torchrun ... -m learn RUN_DIR``: see ``learn.stage.main``.

An entry point, so top floor like the CLI: it loads the study config that the run's config.json is read as.
"""

import clothgap.config  # noqa: F401  (registers StudyConfig for Run.open)
from learn.stage import main

main()
