"""What made the shipped checkpoints and the results: command lines run from the repository
root as ``python -m research.X`` (and ``research.benchmarks``). They import the package; the
package never imports them.

- ``train_image``: notebook 01's or 02's run, longer (the shipped encoders)
- ``train_video``: notebook 03's K ablation, trained and scored
- ``train_world``: notebook 05's world model and its ablations; ``--refit`` a predictor
- ``fit_beyond``: chapter 07's cost head and coarse model on a world model's latents (the fits:
  ``beyond_fits``, on notebook 07's own classes, read from its cells by ``from_notebook``)
- ``sweep``: notebook 02's coefficient and projector sweeps
- ``launch``: what the training commands share to run under torchrun
"""
