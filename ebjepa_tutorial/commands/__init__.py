"""The command lines that train and ship checkpoints (``python -m ebjepa_tutorial.commands.X``).

- ``train_image``: notebook 01's or 02's run, longer (the shipped encoders)
- ``train_video``: notebook 03's K ablation, trained and scored
- ``train_world``: notebook 05's world model and its ablations; ``--refit`` a predictor
- ``sweep``: notebook 02's coefficient and projector sweeps
"""
