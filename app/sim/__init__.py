"""The simulator: rooms of cards rendered through a real lens model, degraded as cameras
degrade images, with ground truth for every disc. Tests, benchmarks and training
measure against it; the service never imports it."""
