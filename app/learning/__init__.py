"""Learning the disc classifier of the candidate stage (`app.core.detection.candidates`).

- `classifier`: fitting the classifier from labelled windows (the screen, Hart's
  condensed nearest neighbour, Gates' reduction, thresholds, held-out statistics).
- `training`: the training windows drawn from the simulator, and the default
  classifier's whole training run (`train_default`).
- `adapt`: extending a classifier with a site's own images, self-labelled by the
  detector (the server's classifier job).
- `labels`: how windows are labelled around true discs, shared by both.

The package re-exports no names: the server imports `adapt`, which must not load the
simulator that `training` needs, so each module is imported by its own name.
"""

__all__ = ["adapt", "classifier", "labels", "training"]
