"""The learn stage: rendered clips -> CNN+LSTM (and the paper's baselines) -> checkpoints.

Entry points: ``learn.stage.run_train(run)`` (the whole grid),
``learn.train.train_one(...)`` (one model), ``python -m learn`` (the grid, also under torchrun),
``learn.predict.predict_clips(...)`` (for eval). Kept import-free: the CLI reads
``learn.config`` at start-up, before torch is needed.
"""
